"""velab's LabJack register table against LabJack's own map (an excerpt of ljm_constants.json, see its "source")."""

import json
from pathlib import Path

import pytest

from velab.drivers import labjack_registers as ljr

MAP = json.loads((Path(__file__).parent / "data" / "ljm_constants_excerpt.json").read_text())
BY_NAME = {r["name"]: r for r in MAP["registers"]}


@pytest.mark.parametrize("name", [n for n, r in ljr.REGISTERS.items() if r.in_map])
def test_register_matches_labjacks_map(name):
    mine, theirs = ljr.REGISTERS[name], BY_NAME.get(name)
    assert theirs is not None, f"{name} is not in LabJack's map"
    assert (mine.address, mine.type, mine.access) == (theirs["address"], theirs["type"], theirs["readwrite"])


def test_registers_outside_the_map_are_the_datasheets_only():
    outside = [n for n, r in ljr.REGISTERS.items() if not r.in_map]
    assert outside == ["STREAM_DATATYPE"]  # datasheet 3.2.4: "not in ljm_constants.json"
    assert "STREAM_DATATYPE" not in BY_NAME
    assert ljr.reg("STREAM_DATATYPE").address == 4018


def test_t7_has_every_register_velab_uses():
    for name, r in ljr.REGISTERS.items():
        if not r.in_map:
            continue
        devices = [d if isinstance(d, str) else d["device"] for d in BY_NAME[name]["devices"]]
        if name != "STREAM_AUTORECOVER_DISABLE":  # T7 / T8 only: the T4 always auto-recovers
            assert "T4" in devices, name
        assert "T7" in devices, name


def test_indexed_families_follow_the_maps_expansion():
    assert ljr.ain(0) == 0 and ljr.ain(1) == 2 and ljr.ain(3) == 6  # FLOAT32: 2 registers per input
    assert ljr.ain_range(1) == 40002
    assert ljr.ain_negative_ch(1) == 41001 and ljr.ain_resolution_index(2) == 41502  # UINT16: 1 register
    assert ljr.fio(3) == 2003
    assert ljr.scanlist_address(1) == 4102
    with pytest.raises(ValueError):
        ljr.fio(8)


def test_stream_status_codes_are_labjacks():
    codes = {e["error"]: e["string"] for e in MAP["errors"]}
    assert codes == ljr.STREAM_STATUS
