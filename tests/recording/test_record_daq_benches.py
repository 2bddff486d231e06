"""The recorder on benches made of products a lab buys: a DATAQ DI-2108 (USB CDC serial) or a LabJack T7 (Modbus
TCP + stream), each firing the valve by its digital line and measuring the position, and the SITRANS flowmeter.

The simulated DAQs speak the vendors' protocols over a real pty / sockets (tests/simulators/test_dataq_sim.py,
test_labjack_sim.py); here the whole run: connect, the readiness checks, arm, fire, record, the measured stroke,
the fit, the file.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest

from record_helpers import cli
from velab.recording import Recorder, RecordSettings
from velab.runfiles.reader import read_run
from velab.simulators.rig import ValveState
from velab.fitting.report import format_report

pytestmark = pytest.mark.slow  # the integration layer: the simulated bench

A_TRUE = 353.73
STROKE = (32.0, -5.5)  # the simulated actuator's own stroke (the rig's nominal: configs/sim/*.toml set no other)


def _record(tmp_path, sim_config, **kw):
    s = RecordSettings(duration_s=kw.pop("duration_s", 6.0), pretrigger_s=kw.pop("pretrigger_s", 1.0), out_dir=tmp_path,
                       **kw)
    with Recorder.simulated(s, sim_config, clock="fast") as rec:
        events = []
        rec.add_listener(events.append)
        summary = rec.run()
        valve = rec.sim.rig.state()
        fired = rec.sim.handles["valve"].fired
    return summary, events, valve, fired


def test_the_dataq_bench_records_a_run_and_names_the_wall(tmp_path):
    summary, events, valve, fired = _record(tmp_path, "dataq", duration_s=22.0, pretrigger_s=2.0)
    assert summary.status == "completed", (summary.status, summary.reason)
    assert summary.lost_samples == 0 and summary.gaps == 0 and fired == 1 and valve is ValveState.DONE
    fit = summary.fit
    # material A is S3 (the recorder's tests on the other bench say why S4/S5 may win by chance: an element that
    # fits the noise, or the stroke's feedback noise); the simpler models never
    assert summary.best_model in ("S3", "S4", "S5"), format_report(fit)
    assert fit["S2"].delta_aic > 10 and fit["S1"].delta_aic > 10
    assert abs(fit["S3"].wave_speed_m_s - A_TRUE) < 0.5
    assert fit.settings["manoeuvre"]["source"] == "position"  # the flow from the measured stroke
    assert fit[summary.best_model].noise_ratio <= 1.5
    # the stroke the actuator made, measured on the DAQ's position channel
    st = summary.stroke
    assert st is not None and abs(st.beta_per_s - STROKE[0]) < 1.0 and abs(st.gamma - STROKE[1]) < 0.5, st
    run = read_run(summary.path)
    assert run.status == "completed" and np.allclose(np.diff(run.time_s), 1e-3)
    with h5py.File(summary.path, "r") as fh:
        man = fh["entry/manoeuvre"]
        assert float(man["measured_beta"][()]) == pytest.approx(st.beta_per_s)
        assert float(man["measured_gamma"][()]) == pytest.approx(st.gamma)
        # each device's identity as the device reports it (DATAQ's `info`)
        ident = json.loads(fh["entry/instrument/devices_json"][()])["daq"]
    assert ident["model"] == "DI-2108" and "5A1B2C3D" in json.dumps(ident), ident


def test_the_labjack_bench_records_a_run_and_measures_the_stroke(tmp_path):
    summary, events, valve, fired = _record(tmp_path, "labjack", duration_s=8.0, fit_window_s=6.0,
                                            fit_models=(0, 1, 2, 3))
    assert summary.status == "completed", (summary.status, summary.reason)
    assert summary.lost_samples == 0 and fired == 1 and valve is ValveState.DONE
    assert summary.best_model == "S3", format_report(summary.fit)
    st = summary.stroke
    assert st is not None and abs(st.beta_per_s - STROKE[0]) < 1.0, st
    with h5py.File(summary.path, "r") as fh:
        ident = json.loads(fh["entry/instrument/devices_json"][()])["daq"]
    assert "470012345" in json.dumps(ident), ident  # the T7's SERIAL_NUMBER as it reports it


def test_a_fired_valve_that_does_not_move_is_a_named_fault(tmp_path):
    """The line fires and the position never leaves the open end (a seized valve, no air): the fired valve's
    FAULT (no stroke seen): the run is aborted and says why; nothing is reported as completed."""
    s = RecordSettings(duration_s=6.0, pretrigger_s=1.0, fit=False, out_dir=tmp_path)
    with Recorder.simulated(s, "dataq", clock="fast") as rec:
        rec.sim.handles["valve"].on_digital = lambda *a, **k: None  # the solenoid's wire cut: nothing moves
        rec.sim.handles["daq"].on_digital = None
        summary = rec.run()
    assert summary.status in ("aborted", "completed-with-faults"), (summary.status, summary.reason)
    assert "no stroke" in summary.reason, summary.reason


def test_a_commanded_manoeuvre_is_refused_for_a_fired_valve(tmp_path):
    """A fired actuator's stroke is its own: a --beta for it is bad input, refused before anything moves."""
    out = cli(["record", "--simulate", "--fast", "--beta", "40", "--no-fit", "--duration", "3",
               "--out-dir", str(tmp_path)])
    assert out.returncode == 2, (out.returncode, out.stderr)
    errors = [x for x in out.stderr.splitlines() if x.startswith("velab:")]  # (the progress lines before it)
    assert len(errors) == 1 and "fired" in errors[0], out.stderr
    assert not list(tmp_path.glob("*.h5"))


@pytest.mark.parametrize("config", ["dataq", "labjack"])
def test_velab_record_config_against_velab_sim_serving_the_bench(tmp_path, config):
    """velab sim serves the DATAQ bench (a pty, as a USB CDC device appears) or the LabJack one (Modbus TCP and the
    stream port); velab record --config reaches it by the bench config velab sim prints; the run completes."""
    sim = subprocess.Popen([sys.executable, "-m", "velab.cli", "sim", "--config", config, "--ephemeral", "--json"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = sim.stdout.readline()
        assert line, sim.stderr.read()
        doc = json.loads(line)
        daq = doc["bench"]["devices"]["daq"]
        if config == "dataq":
            assert daq["url"].startswith("/")  # the pty's link
        else:
            assert daq["port"] and daq["stream_port"] and daq["host"] == "127.0.0.1"
        bench = tmp_path / "bench.toml"
        bench.write_text(doc["bench_toml"])
        out = subprocess.run([sys.executable, "-m", "velab.cli", "record", "--config", str(bench), "--no-fit",
                              "--duration", "4", "--pretrigger", "1", "--out-dir", str(tmp_path), "--json"],
                             capture_output=True, text=True, timeout=180)
        assert out.returncode == 0, (out.returncode, out.stderr[-2000:])
        res = json.loads(out.stdout)["runs"][0]
        assert res["status"] == "completed" and res["stroke"] is not None, res
    finally:
        sim.terminate()
        try:
            sim.wait(20)
        except subprocess.TimeoutExpired:
            sim.kill()
            time.sleep(0.1)
