"""velab.benchrig / velab.config.with_valve_profile: MV's characteristic from the valve's device profile."""

import logging
from pathlib import Path

import numpy as np
import pytest
from record_helpers import recorder, run_bounded, short_settings, thread_errors  # noqa: F401 (fixture)

from velab.benchrig import rig_for_bench, valve_profile_name
from velab.config import load_rig, with_valve_profile
from velab.configpath import load_config
from velab.drivers.bench import load_bench
from velab.drivers.profile import load_profile
from velab.errors import ConfigError
from velab.rig import rig_from_dict
from velab.runfiles import read_run
from velab.simulators.bench import SimulatedBench
from velab.simulators.clock import ManualClock, make_clock

ACTUATOR = Path(__file__).resolve().parents[1] / "configs" / "devices" / "valve_actuator.toml"
TABLE = """
[valve]
characteristic = "table"
position_pct = [0, 20, 40, 60, 80, 100]
flow_ratio = [0, 0.05, 0.19, 0.42, 0.74, 1.0]
"""


def profile_with(tmp_path, valve_table: str, name="my_valve"):
    """The built-in actuator profile with another [valve] table (a lab's valve)."""
    text = ACTUATOR.read_text()
    text = text[: text.index("\n[valve]\n")] + "\n" + valve_table
    p = tmp_path / f"{name}.toml"
    p.write_text(text)
    return p


def test_the_built_in_bench_takes_the_butterfly_from_the_actuators_profile():
    bench = load_bench("sim")
    assert valve_profile_name(bench.devices, bench.recorder.get("valve")) == "valve_actuator"
    rig = rig_for_bench(load_rig("perugia"), bench.devices, bench.recorder.get("valve"))
    assert rig.valve.characteristic == "butterfly"
    assert rig.valve.characteristic_from == "profile valve_actuator"
    assert "from the valve's profile valve_actuator" in rig.valve.describe()


def test_a_profiles_table_replaces_the_default_and_is_stored_with_the_rig(tmp_path):
    rig = with_valve_profile(load_rig("perugia"), load_profile(profile_with(tmp_path, TABLE)))
    v = rig.valve
    assert v.characteristic == "table" and v.position_pct == (0, 20, 40, 60, 80, 100)
    assert v.characteristic_from == "profile my_valve"
    assert v.series_loss_share == 0.05  # the rig's: the throttle's share is the rig's, not the valve's
    assert np.isclose(v.flow_ratio_at(60.0), 0.42)
    back = rig_from_dict(rig.to_dict())
    assert back.valve == v


def test_a_rig_that_names_its_characteristic_keeps_it_and_the_difference_is_logged(tmp_path, caplog):
    rig_file = tmp_path / "linear.toml"
    rig_file.write_text(Path(load_rig("perugia").source).read_text().replace(
        'law = "orifice"', 'law = "orifice"\ncharacteristic = "linear"'))
    rig = load_rig(rig_file)
    assert rig.valve.characteristic_from == "rig"
    with caplog.at_level(logging.WARNING, logger="velab.config"):
        kept = with_valve_profile(rig, load_profile(profile_with(tmp_path, TABLE)))
    assert kept.valve.characteristic == "linear"
    assert "differs from the valve's profile my_valve" in caplog.text


@pytest.mark.parametrize("table, match", [
    ('[valve]\ncharacteristic = "power"\n', r"my_valve\.toml: \[valve\] exponent: missing key"),
    ('[valve]\ncharacteristic = "table"\nposition_pct = [0, 50, 40, 100]\nflow_ratio = [0, 0.2, 0.5, 1]\n',
     r"my_valve\.toml: \[valve\] position_pct: "),
    ('[valve]\ncharacteristic = "gate"\n', r"my_valve\.toml: \[valve\] characteristic: "),
    ('[valve]\nexponent = 2.0\n', r"my_valve\.toml: \[valve\] characteristic: missing key"),
    ('[valve]\ncharacteristic = "linear"\nseries_loss_share = 0.2\n', r"my_valve\.toml: \[valve\] series_loss_share: unknown key"),
])
def test_a_bad_profile_table_is_one_line_naming_the_file_and_key(tmp_path, table, match):
    with pytest.raises(ConfigError, match=match) as err:
        with_valve_profile(load_rig("perugia"), load_profile(profile_with(tmp_path, table)))
    assert "\n" not in str(err.value)


def test_the_simulated_rigs_valve_follows_its_profile(tmp_path):
    _, config = load_config("sim", "default")
    config["devices"]["valve"]["profile"] = str(profile_with(tmp_path, TABLE))
    with SimulatedBench(config, clock=ManualClock(), ephemeral=True) as sim:
        v = sim.rig.rig.valve
        assert v.characteristic == "table" and v.characteristic_from == "profile my_valve"
        # the physics of the simulated rig uses it: its flow through the valve at 60 % open
        assert np.isclose(sim.rig.rig.valve.flow_ratio_at(60.0), 0.42)


@pytest.mark.slow
def test_a_recorded_run_stores_the_valve_profiles_characteristic(tmp_path, thread_errors):
    """The recorder takes the rig through velab.benchrig: the run file's rig carries the bench's valve
    (here a table in the valve's profile, the rig file naming none) and says where it came from."""

    _, config = load_config("sim", "default")
    config["devices"]["valve"]["profile"] = str(profile_with(tmp_path, TABLE))
    sim = SimulatedBench(config, ephemeral=True, clock=make_clock("fast")).start()
    out = run_bounded(recorder(sim, short_settings(tmp_path)))
    assert out.summary is not None and out.summary.status == "completed", out
    v = read_run(out.summary.path).rig.valve
    assert v.characteristic == "table" and v.characteristic_from == "profile my_valve"
    assert not thread_errors
