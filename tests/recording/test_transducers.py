"""velab.recording.transducers alone: the bench's channel map ([recorder.transducers]) against the rig's
transducers and the pressure source's channels (no devices): the default for the valve's transducer, the
run file's channel names, and every config error as one line naming the file, the table and the key."""

from __future__ import annotations

import pytest

from velab.config import load_rig
from velab.errors import ConfigError
from velab.recording.layout import fast_channels
from velab.recording.transducers import transducer_channels
from velab.rig import Section

BENCH = "benches/lab.toml"
PRESSURE = ("pressure", "pressure_2", "pressure_3")


@pytest.fixture(scope="module")
def two():
    return load_rig("perugia_two_sections")


def test_a_rig_with_one_transducer_needs_nothing_new():
    (valve,) = transducer_channels(load_rig("perugia"), {}, BENCH, PRESSURE)
    assert (valve.name, valve.adc_channel, valve.head, valve.at_valve) == ("valve", "pressure", "head", True)
    assert valve.position_m == 102.58 and valve.channel("pressure_quality") == "pressure_quality"


def test_the_valves_transducer_first_on_the_first_pressure_channel_the_others_as_mapped(two):
    valve, mid = transducer_channels(two, {"mid": "pressure_3"}, BENCH, PRESSURE)
    assert (valve.name, valve.adc_channel, valve.head) == ("valve", "pressure", "head")
    assert (mid.name, mid.adc_channel, mid.head, mid.position_m) == ("mid", "pressure_3", "head_mid", 41.032)
    assert [mid.channel(b) for b in ("head", "pressure", "pressure_raw", "pressure_quality")] == [
        "head_mid", "pressure_mid", "pressure_raw_mid", "pressure_quality_mid"]
    # the head channels are the ones velab synth writes and the fit reads (Rig.section_channel)
    assert [t.head for t in (valve, mid)] == [two.section_channel(s) for s in two.sections]


def test_the_valves_transducer_may_be_named_too(two):
    valve, mid = transducer_channels(two, {"valve": "pressure_2", "mid": "pressure"}, BENCH, PRESSURE)
    assert valve.adc_channel == "pressure_2" and mid.adc_channel == "pressure"


def test_the_run_files_channels_of_each_transducer(two):
    names = {c.name: c.group for c in fast_channels(transducer_channels(two, {"mid": "pressure_2"}, BENCH))}
    assert names["head_mid"] == "data" and names["head"] == "data"
    assert names["pressure_mid"] == names["pressure_quality_mid"] == "instrument/pressure_transducer_mid"
    assert set(fast_channels()) < set(fast_channels(transducer_channels(two, {"mid": "x"}, BENCH)))


@pytest.mark.parametrize("mapping, channels, says", [
    ({}, PRESSURE, "[recorder.transducers]: no channel for the transducer 'mid' at 41.032 m"),
    ({"mid": "pressure_2", "upstream": "pressure_3"}, PRESSURE,
     "[recorder.transducers] upstream: the rig 'Perugia HDPE DN110 PN10, two sections' has no transducer 'upstream'"),
    ({"mid": "valve_position"}, PRESSURE,
     "[recorder.transducers] mid: 'valve_position' is not a pressure channel (units Pa) of adc"),
    ({"mid": "pressure"}, PRESSURE, "[recorder.transducers] mid: channel 'pressure' is taken by the transducer 'valve'"),
    ({"mid": "pressure_2"}, (), "[recorder.transducers] mid: 'pressure_2' is not a pressure channel"),
])
def test_config_errors_are_one_line_naming_the_bench_the_table_and_the_key(two, mapping, channels, says):
    with pytest.raises(ConfigError) as e:
        transducer_channels(two, mapping, BENCH, channels, "adc")
    assert str(e.value).startswith(f"{BENCH}: ") and says in str(e.value) and "\n" not in str(e.value)


def test_without_the_sources_channels_only_the_names_are_checked(two):
    assert transducer_channels(two, {"mid": "anything"}, BENCH)[1].adc_channel == "anything"
    with pytest.raises(ConfigError, match="no channel for the transducer 'mid'"):
        transducer_channels(two, {}, BENCH)


def test_a_transducer_whose_channels_would_clash_with_the_valves_is_refused(two):
    rig = two.with_changes(transducers=(Section("valve", 102.58), Section("raw", 50.0)))
    with pytest.raises(ConfigError, match="transducer 'raw' would be recorded as 'pressure_raw'"):
        transducer_channels(rig, {"raw": "pressure_2"}, BENCH, PRESSURE)
