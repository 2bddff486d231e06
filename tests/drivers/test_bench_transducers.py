"""A bench file's channel map, ``[recorder.transducers]`` (velab.drivers.bench): read and checked, one line
naming the file, the table and the key for a bad one; written back by ``to_toml``; a sim config's
``[recorder]`` table reaches the bench its simulator serves (velab.simulators.bench)."""

from __future__ import annotations

import pytest

from velab.configpath import find_config
from velab.drivers.base import ProfileError
from velab.drivers.bench import Bench, load_bench
from velab.errors import ConfigError
from velab.simulators.bench import SimulatedBench

DEVICES = '[devices.adc]\nkind = "streaming_adc"\nurl = "socket://127.0.0.1:1"\n'


def _bench(tmp_path, recorder: str) -> Bench:
    path = tmp_path / "lab.toml"
    path.write_text(recorder + "\n" + DEVICES)
    return load_bench(path)


def test_the_built_in_two_sections_bench_maps_mid():
    b = load_bench("sim_two_sections")
    assert b.transducer_channels == {"mid": "pressure_2"} and b.recorder["pressure_source"] == "streaming_adc"
    assert b.devices["streaming_adc"].profile == "streaming_adc_sections"


def test_a_bench_without_the_table_maps_nothing(tmp_path):
    assert _bench(tmp_path, '[recorder]\npressure_source = "adc"').transducer_channels == {}
    assert load_bench("sim").transducer_channels == {}


def test_the_table_survives_to_toml(tmp_path):
    b = _bench(tmp_path, '[recorder]\npressure_source = "adc"\n[recorder.transducers]\nmid = "pressure_2"\nup = "p3"')
    again = tmp_path / "again.toml"
    again.write_text(b.to_toml())
    assert load_bench(again).transducer_channels == {"mid": "pressure_2", "up": "p3"}


@pytest.mark.parametrize("recorder, says", [
    ('[recorder.transducers]\nmid = 2', "[recorder.transducers] mid: must be a string, got int 2"),
    ('[recorder.transducers]\nmid = ""', "[recorder.transducers] mid: must name a channel of the pressure source"),
    ('[recorder]\ntransducers = "mid"', "[recorder] transducers: must be a table, got str 'mid'"),
    ('[recorder]\nchannels = {mid = "p"}', "[recorder] channels: unknown key"),
])
def test_a_bad_table_is_one_line_naming_the_file_the_table_and_the_key(tmp_path, recorder, says):
    with pytest.raises(ProfileError) as e:
        _bench(tmp_path, recorder)
    msg = str(e.value)
    assert msg.startswith(str(tmp_path / "lab.toml")) and says in msg and "\n" not in msg
    assert isinstance(e.value, ConfigError)  # `velab record --config` exits 2 with it


def test_a_sim_configs_recorder_table_is_the_bench_it_serves():
    sim = SimulatedBench.from_config("two_sections", ephemeral=True)  # (not started: no endpoints, no bench devices)
    assert sim.recorder == {"transducers": {"mid": "pressure_2"}}
    assert sim.bench().transducer_channels == {"mid": "pressure_2"}


def test_a_bad_recorder_table_in_a_sim_config_names_the_file(tmp_path):
    text = find_config("sim", "two_sections").read_text().replace('mid = "pressure_2"', "mid = 2")
    path = tmp_path / "sim.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as e:
        SimulatedBench.from_config(path, ephemeral=True)
    assert str(e.value).startswith(str(path)) and "[recorder.transducers] mid: must be a string" in str(e.value)
