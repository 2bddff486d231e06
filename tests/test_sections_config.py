"""[[transducers]] in a rig file: parsed, checked (one line naming file, table, key), stored with the rig."""

import pytest

from velab.config import load_rig
from velab.errors import ConfigError
from velab.rig import Section, rig_from_dict

BASE = (__import__("pathlib").Path(__file__).parents[1] / "configs" / "rigs" / "perugia.toml").read_text()


def _rig(tmp_path, extra: str):
    p = tmp_path / "two.toml"
    p.write_text(BASE + extra)
    return p


TWO = """
[[transducers]]
name = "valve"
position_m = 102.58

[[transducers]]
name = "mid"
position_m = 41.03
"""


def test_rig_without_the_table_has_the_valve_section():
    rig = load_rig("perugia")
    assert rig.transducers == ()
    assert rig.sections == (Section("valve", rig.pipe.length_m),)


def test_two_transducers_parsed_and_round_tripped(tmp_path):
    rig = load_rig(_rig(tmp_path, TWO))
    assert rig.sections == (Section("valve", 102.58), Section("mid", 41.03))
    assert rig_from_dict(rig.to_dict()) == rig


def test_a_stored_rig_without_transducers_reads_as_the_valve_one():
    d = load_rig("perugia").to_dict()
    d.pop("transducers")
    assert rig_from_dict(d).sections == (Section("valve", 102.58),)


@pytest.mark.parametrize("extra, where, reason", [
    ('\n[[transducers]]\nname = "a"\nposition_m = 0.0\n', "[[transducers]] #1 position_m", "must be in (0, 102.58]"),
    ('\n[[transducers]]\nname = "a"\nposition_m = 103.0\n', "[[transducers]] #1 position_m", "must be in (0, 102.58]"),
    ('\n[[transducers]]\nname = "a"\nposition_m = 10.0\n[[transducers]]\nname = "a"\nposition_m = 20.0\n',
     "[[transducers]] #2 name", "already the name"),
    ('\n[[transducers]]\nposition_m = 10.0\n', "[[transducers]] #1 name", "missing key"),
    ('\n[[transducers]]\nname = "a"\nposition_m = 10.0\nchannel = 2\n', "[[transducers]] #1 channel", "unknown key"),
    ('\n[[transducers]]\nname = " "\nposition_m = 10.0\n', "[[transducers]] #1 name", "must be letters"),
    ('\n[[transducers]]\nname = "a/b"\nposition_m = 10.0\n', "[[transducers]] #1 name", "must be letters"),
])
def test_bad_transducers_are_one_line_naming_file_table_key(tmp_path, extra, where, reason):
    p = _rig(tmp_path, extra)
    with pytest.raises(ConfigError) as exc:
        load_rig(p)
    msg = str(exc.value)
    assert "\n" not in msg and str(p) in msg and where in msg and reason in msg, msg


def test_channels_and_steady_heads(tmp_path):
    rig = load_rig(_rig(tmp_path, TWO))
    valve, mid = rig.sections
    assert rig.head_section == valve
    assert [rig.section_channel(s) for s in rig.sections] == ["head", "head_mid"]
    assert rig.steady_head_at_m(rig.pipe.length_m) == rig.steady_head_m
    assert rig.steady_head_at_m(41.03) == pytest.approx(rig.reservoir_head_m - rig.steady_head_loss_m * 41.03 / 102.58)
