"""velab record / velab.Recorder end to end against the simulated rig (real sockets, fast clock).

The simulated rig runs on one ScaledClock (12 x real time) shared by the valve, the
streaming ADC's sample clock and the flowmeter: a 2 s + 22 s run takes ~2 s of wall time.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from record_helpers import cli, rate_clock
from velab.errors import SafetyError, VelabError
from velab.recording import Recorder, RecordSettings, RunRefused
from velab.runfiles.reader import read_run
from velab.fitting.report import format_report

pytestmark = pytest.mark.slow  # the integration layer: the simulated bench (tests/recording: the stages alone)

A_TRUE = 353.73


def _paper_friction_sim_config(tmp_path) -> str:
    """The default simulated bench on the reference rig with the paper's *linear* friction.

    The simulated rig now makes its heads with the rig's quadratic friction; until the
    calibration represents it (issue 10, the fitter's part), an online fit of such data
    picks S2 for material A. The model-selection tests below check the recorder's fit on
    data its model can represent; switch them back to the default bench with the fitter's change.
    """
    from velab.configpath import find_config

    rig = find_config("rigs", "perugia").read_text()
    assert 'friction = "quadratic"' in rig
    (tmp_path / "rig_linear.toml").write_text(rig.replace('friction = "quadratic"', 'friction = "linear"'))
    sim = find_config("sim", "default").read_text()
    assert 'rig = "perugia"' in sim
    (tmp_path / "sim_linear.toml").write_text(sim.replace('rig = "perugia"', f'rig = "{tmp_path / "rig_linear.toml"}"'))
    return str(tmp_path / "sim_linear.toml")


def _run(tmp_path, material, *, sim_config="default", clock="fast", **kw):
    s = RecordSettings(duration_s=kw.pop("duration_s", 22.0), out_dir=tmp_path, **kw)
    with Recorder.simulated(s, sim_config, material=material, clock=clock) as rec:
        events = []
        rec.add_listener(events.append)
        summary = rec.run()
        valve_state = rec.sim.rig.state().name if rec.sim else None
    return summary, events, valve_state


def _stroke_element(fit, smaller: str) -> bool:
    """The best model is ``smaller`` plus one element faster than the closure that holds under 1e-3 of
    ``smaller``'s compliance: the recorded position's noise during the stroke, not the wall
    (docs/fitting.md, the "position" manoeuvre)."""
    best, small = fit.best, fit[smaller]
    if best.m != small.m + 1:
        return False
    closure_s = 10.0 * fit.settings["bounds"]["tau_min_s"]  # (tau_min = a tenth of the closure time)
    extra = min(range(best.m), key=lambda i: best.J_rel[i])
    return (best.tau_s[extra] < closure_s and best.J_rel[extra] < 1e-3 * sum(small.J_rel)
            and any("noise during the stroke" in n for n in fit.notes))  # (and the fit says so)


def test_material_A_online_fit_names_S3(tmp_path):
    summary, events, _ = _run(tmp_path, "A", sim_config=_paper_friction_sim_config(tmp_path))
    assert summary.status == "completed" and summary.exit_code == 0, (summary.status, summary.reason)
    assert summary.lost_samples == 0 and summary.gaps == 0
    fit = summary.fit
    # AIC names the truth, S3, on most recordings (8 in 10 when measured on 25 Nov). Otherwise S4
    # wins: (1) a fourth element fits a little of the noise, a chance chi-square gain on two parameters
    # that puts S3 more than 2 behind on 5 % of recordings and more than 10 behind on 0.2 %; (2) an element
    # faster than the closure fits the stroke's feedback noise (below, S1's test). The steady head's error
    # no longer adds a third reason: the baseline's mean (2 s here, sigma 0.012 m / sqrt(2000) = 0.27 mm) was
    # the steady head, and a slow element (a ramp on the 200 s bound, or the slowest split in two) made up for
    # a mean set too high -- on 166 recordings of this bench (28 Nov), one 2.3 standard errors high put S3
    # 18.2 behind S5, one 1.6 high 10.2 behind S4. Every model now fits the steady head's offset, the baseline
    # its prior (velab.fitting.offset): refitted, those two have S3 4.4 and 1.0 behind, and no recording of
    # the 63 refitted (the worst 30 and 33 others) more than 6.0. S1 and S2 are ruled out every time.
    assert summary.best_model in ("S3", "S4", "S5")
    if summary.best_model == "S5":
        assert _stroke_element(fit, "S4"), format_report(fit, elements=True)
    assert fit["S3"].delta_aic <= 10.0 or _stroke_element(fit, "S3"), format_report(fit, elements=True)
    # the steady head's offset is the baseline mean's error: a few of its standard errors at most
    assert abs(fit.best.steady_head_offset_m) < 4 * 0.012 / np.sqrt(2000), format_report(fit)
    assert fit["S2"].delta_aic > 10 and fit["S1"].delta_aic > 10
    assert abs(fit["S3"].wave_speed_m_s - A_TRUE) < 0.5
    # the simulated valve is a real one (orifice law): the fit took the manoeuvre from the measured
    # position and describes the record at its noise (issue 24)
    assert fit.settings["manoeuvre"]["source"] == "position"
    assert fit[summary.best_model].noise_ratio <= 1.5 and not [w for w in fit.warnings if w["code"] == "misfit"]
    # the run file: completed, the fit stored, the time axis from the device clock, trigger measured
    run = read_run(summary.path)
    assert run.status == "completed" and not run.incomplete
    assert run.n_samples == summary.n_samples
    assert np.allclose(np.diff(run.time_s), 1e-3)
    # measured from the valve position, next to the recorder's estimate at the command. The estimate is the
    # host's: the command may go out late on a loaded machine, and at the fast clock (12 x) 0.1 s of host time
    # is 1.2 s here (0.28-0.32 s was seen on a loaded 2-core host, 1.32 s with two other suites running); the
    # measured instant is what the file keeps: the bound says the two name the same closure (0.2 s of host time)
    estimates = [e.data["trigger_time_s"] for e in events if e.kind == "trigger" and e.data.get("measured") is False]
    assert len(estimates) == 1 and abs(run.trigger_time_s - estimates[0]) < 2.4, (run.trigger_time_s, estimates)
    assert "online" in run.fit_names
    assert {"valve_position", "pressure", "pressure_raw", "sample_index", "host_time"} <= set(run.channels)
    assert np.array_equal(run.channels["sample_index"], np.arange(run.n_samples))
    kinds = {k for _, k, _ in run.events}
    assert {"operator", "trigger", "status"} <= kinds
    with h5py.File(summary.path, "r") as fh:
        settings = json.loads(fh["entry/notes/settings_json"][()])
        assert settings["duration_s"] == 22.0
        assert fh["entry/instrument/flow/value"].shape[0] > 0
        assert fh["entry/fits/online/best"].asstr()[()] == summary.best_model
    # the peak: Joukowsky over the steady head, within the interlock's prediction
    assert run.rig.steady_head_m + 0.8 * run.rig.joukowsky_head_m() < summary.peak_head_m
    # live events: phases in order, samples in order, a final fit
    phases = [e.data["phase"] for e in events if e.kind == "phase"]
    for p in ("ready", "armed", "triggerable", "recording", "completed"):
        assert p in phases
    t = np.concatenate([e.data["time_s"] for e in events if e.kind == "samples"])
    assert t.size == summary.n_samples and np.all(np.diff(t) > 0)
    finals = [e for e in events if e.kind == "fit" and e.data["final"]]
    assert len(finals) == 1 and finals[0].data["result"].best.name == summary.best_model
    assert events[-1].kind == "done"


def test_s1_material_is_not_named_s3(tmp_path):
    summary, _, _ = _run(tmp_path, "hdpe_s1", sim_config=_paper_friction_sim_config(tmp_path), fit_models=(0, 1, 2, 3))
    assert summary.status == "completed", (summary.status, summary.reason)
    fit = summary.fit
    s1 = fit["S1"]
    # The truth keeps support. By chance alone an extra element gains n ln F, and its retardation time is free
    # over [tau_min, tau_max] where the truth has no element: under S1 that time is not identified, so the gain
    # is the largest of many chi2(2) tries and has a heavier tail than chi2(2) (Davies, Biometrika 1987).
    # Measured on 140 recordings of this bench (29 Nov, 60 alone and 80 beside two suites): S1's dAIC mean
    # -2.1 (chi2(2) - 4 gives -2), sd 3.2 (chi2(2): 2); beyond 5.8 in 6, of which 2 by an element that is not
    # the stroke's (a ramp on the 200 s bound at 6.97, a split of S1's element at 5.85); the suite saw 8.5 once
    # (2 of ~18 runs with two suites at once failed the old bound, 7). 12 is chi2(2)'s 0.03 % point.
    # The recorded valve position adds one more way: its feedback noise (0.02 %) during the stroke enters the
    # flow at the valve, and the wavefront error it leaves repeats every period; in 2 of 100 simulated records
    # an element faster than the closure fitted it, S1 16-21 behind (docs/fitting.md, "position"). That
    # element holds ~1e-4 of the compliance: the creep function is S1's either way, and nothing else may win.
    assert summary.best_model in ("S1", "S2"), format_report(fit, elements=True)
    assert s1.delta_aic < 12.0 or _stroke_element(fit, "S1"), format_report(fit, elements=True)
    assert fit["EL"].delta_aic > 10
    assert abs(s1.wave_speed_m_s - A_TRUE) < 0.5


def test_the_run_is_built_on_the_rate_the_adc_samples_at(tmp_path):
    """7000 Hz is not a divisor of the streaming ADC's 10 MHz clock: it samples at 6997.9 Hz. The run file's
    time axis (and so the wave speed) is built on that rate, not the one asked for (it was: 0.03 % off)."""
    from velab.drivers.sadc_protocol import actual_rate

    summary, events, _ = _run(tmp_path, "A", duration_s=1.0, fit=False, sample_rate_hz=7000.0,
                              clock=rate_clock(7000.0))
    assert summary.status == "completed", summary.reason
    fs = actual_rate(7000.0)
    assert abs(fs - 7000.0) > 1.0
    run = read_run(summary.path)
    assert run.sample_rate_hz == pytest.approx(fs, rel=1e-7)  # (the device's RATE reply has three decimals)
    assert np.diff(run.time_s) == pytest.approx(1.0 / fs, rel=1e-7)
    assert any(e.kind == "message" and f"samples at {fs:.6g} Hz (asked 7000 Hz)" in str(e.data) for e in events)


def test_interlock_refuses_an_unsafe_manoeuvre_before_anything_moves(tmp_path):
    s = RecordSettings(duration_s=3, fit=False, out_dir=tmp_path, surge_margin=1.0)
    with Recorder.simulated(s, clock="fast") as rec:
        pred = rec.predict_surge()
        assert not pred.allowed and pred.limiting == "transducer full scale"
        assert "refused" in pred.message
        with pytest.raises(SafetyError, match="refused"):
            rec.run()
        assert rec.sim.rig.trigger_count == 0 and rec.sim.rig.state().name == "IDLE"
    assert list(tmp_path.iterdir()) == []


def test_a_ceiling_below_the_predicted_peak_is_refused_before_anything_moves(tmp_path):
    """An abort after the closure cannot stop the surge: a ceiling the predicted peak reaches is refused at arm
    (exit 3), the valve never armed, no run file (issue 50; it used to warn and close the valve anyway)."""
    s = RecordSettings(duration_s=3, fit=False, out_dir=tmp_path, ceiling_head_m=40.0)
    with Recorder.simulated(s, clock="fast") as rec:
        pred = rec.predict_surge()
        assert not pred.allowed and pred.over_ceiling and pred.ceiling_m == 40.0 and pred.peak_head_m > 40.0
        with pytest.raises(RunRefused, match="reaches the pressure ceiling 40.0 m"):
            rec.run()
        assert rec.sim.rig.trigger_count == 0 and rec.sim.rig.state().name == "IDLE"
    assert list(tmp_path.iterdir()) == []


def test_pressure_ceiling_aborts_and_holds_the_valve(tmp_path):
    # a head the interlock did not predict (a measured 19.5 mA, within NE43: a measurement near full scale,
    # from 0.1 s after the trigger) crosses a ceiling above the predicted peak: the run is aborted while
    # the valve still closes. Real time: on the fast clock a loaded host stopped a valve that had closed.
    from velab.configpath import find_config

    cfg = tmp_path / "surge.toml"
    cfg.write_text(find_config("sim", "default").read_text() + '\n[[faults.schedule]]\ndevice = "rig"\n'
                   'fault = { channel_mA = { 0 = 19.5 } }\nat = "trigger+0.1"\nduration_s = 0.5\n')
    summary, events, valve_state = _run(tmp_path, "A", sim_config=str(cfg), duration_s=1.5, fit=False,
                                        ceiling_head_m=56.0, clock="realtime")
    assert summary.status == "aborted" and summary.exit_code == 4
    assert "pressure ceiling" in summary.reason
    assert valve_state in ("ABORTED", "HOLDING")
    run = read_run(summary.path)
    assert run.status == "aborted" and "pressure ceiling" in run.status_reason
    assert run.head_m.max() > 56.0  # recorded up to the end, the crossing included


def test_cli_a_manoeuvre_outside_the_actuators_profile_is_bad_input_and_writes_nothing(tmp_path):
    """--beta 5000 against the actuator profile's maximum 200: exit 2, one line naming it, no run file (it was
    a device failure, exit 5, with a "failed" run file); --ceiling under the predicted peak: exit 3, none."""
    for extra, code, said in ((["--beta", "5000"], 2, "beta = 5000.0 1/s is above the profile maximum 200"),
                              (["--ceiling", "40"], 3, "reaches the pressure ceiling 40.0 m")):
        out = cli(
            # the servo actuator's bench (its profile's range; a fired valve takes no manoeuvre at all:
            # tests/recording/test_record_daq_benches.py)
            ["record", "--simulate", "--sim-config", "default", "--fast",
             "--duration", "3", "--no-fit", "--out-dir", str(tmp_path), *extra])
        assert out.returncode == code, out.stderr
        errors = [line for line in out.stderr.splitlines() if line.startswith("velab:")]
        assert len(errors) == 1 and said in errors[0] and "Traceback" not in out.stderr, out.stderr
        assert [p.name for p in tmp_path.iterdir() if not p.name.startswith(".")] == []


@pytest.mark.parametrize("where", ["missing", "proc"])
def test_unwritable_output_directory_is_refused(tmp_path, where):
    out = tmp_path / "nope" if where == "missing" else Path("/proc/self")
    s = RecordSettings(duration_s=3, fit=False, out_dir=out)
    with Recorder.simulated(s, clock="fast") as rec:
        with pytest.raises(RunRefused, match="output directory"):
            rec.run()
        assert rec.sim.rig.trigger_count == 0 and rec.sim.rig.state().name == "IDLE"


def test_cli_json_campaign(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "velab.cli", "record", "--simulate", "--fast", "--duration", "3", "--window", "2",
         "--models", "1,3", "--repeat", "2", "--json", "--quiet", "--out-dir", str(tmp_path)],
        capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stderr
    doc = json.loads(out.stdout)
    assert doc["exit_code"] == 0 and len(doc["runs"]) == 2
    assert doc["campaign"]["statuses"] == ["completed", "completed"]
    names = sorted(p.name for p in tmp_path.glob("*.h5"))
    assert len(names) == 2 and names[0].endswith("_run001.h5") and names[1].endswith("_run002.h5")


def test_cli_simulate_with_another_rig_simulates_that_rig(tmp_path):
    """`--simulate --rig NAME`: the simulated rig is that rig (its Q0, geometry), so the readiness checks pass
    and the run file names it; it used to run the sim config's rig and refuse on the steady flow."""
    out = subprocess.run(
        [sys.executable, "-m", "velab.cli", "record", "--simulate", "--fast", "--rig", "imperial", "--duration", "3",
         "--no-fit", "--json", "--quiet", "--out-dir", str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    run = read_run(json.loads(out.stdout)["runs"][0]["path"])
    assert run.status == "completed" and "imperial" in run.rig.name.lower()
    with h5py.File(run.path, "r") as fh:
        measured = float(fh["entry/manoeuvre/measured_steady_flow"][()])
    assert measured == pytest.approx(run.rig.steady_flow_m3_s, rel=0.05)  # the simulator's flow is the rig's


def test_cli_refusal_exit_code_and_one_line_error(tmp_path):
    out = cli(["record", "--simulate", "--fast", "--duration", "3", "--no-fit", "--surge-margin", "1.0",
                "--out-dir", str(tmp_path)])
    assert out.returncode == 3
    assert "Traceback" not in out.stderr and "refused" in out.stderr
    bad = cli(["record", "--simulate", "--duration", "3", "--window", "20", "--out-dir", str(tmp_path)])
    assert bad.returncode == 2 and "Traceback" not in bad.stderr


def _trigger_when_baseline_is_in(rec, timeout=30.0):
    deadline = time.monotonic() + timeout
    while True:
        try:
            rec.trigger().result(timeout=30)
            break
        except VelabError as exc:  # "baseline not complete": retry (bounded)
            if "baseline" not in str(exc) or time.monotonic() > deadline:
                raise
            time.sleep(0.02)
    return rec.wait(60)


def test_second_run_on_the_same_connection_after_reset_valve(tmp_path):
    """A finished recorder re-arms on the same connection once the valve is reset (reopened);
    the measured trigger instant is published as soon as it is known."""
    # The record ends `duration_s` after the stroke's latest start as the blocks bound it (the device's index at the
    # TRIGGER's reply), which is behind the true start by the least delay of any block (x 12 at the fast clock):
    # "no stroke seen" if that exceeds the record less the stroke. A 2-3 s record (0.17-0.25 s of host time) did on
    # another 2-core host; 6 and 5 s left 0.47 and 0.39 s of host time, where a host at load 25 was measured 0.17 s
    # late. Records of 15 and 12 s (1.25 and 1 s of host time) leave at least 0.9 s.
    s = RecordSettings(duration_s=15.0, pretrigger_s=0.5, fit=False, out_dir=tmp_path)
    with Recorder.simulated(s, clock="fast") as rec:
        events = []
        rec.add_listener(events.append)
        first = rec.run()
        assert first.status == "completed", (first.status, first.reason)
        devices = dict(rec.devices)
        valve = [e.data for e in events if e.kind == "valve"]
        assert valve[-1]["open"] is False and rec.valve_open is False  # closed by the manoeuvre
        # the measured trigger came as its own event, before the end, and is the run's trigger time
        kinds = [e.kind for e in events]
        # (a loaded host may fill the baseline after the run's own trigger call: a "queued" event first)
        trigger = [(i, e.data) for i, e in enumerate(events) if e.kind == "trigger" and not e.data.get("queued")]
        measured = [i for i, d in trigger if d["measured"]]
        assert len(measured) == 1 and measured[0] < kinds.index("done")
        assert events[measured[0]].data["trigger_time_s"] == first.trigger_time_s
        # the command's estimate first, unless the feedback measured the instant before the TRIGGER's reply came
        # (a loaded host: its reply late, the valve already moving): then only the measured one
        assert [d["measured"] for _, d in trigger] in ([False, True], [True])
        # arming with the valve closed is refused (nothing moves), and says what to do
        with pytest.raises(RunRefused, match="valve not open"):
            rec.arm().result(timeout=60)
        assert rec.sim.rig.trigger_count == 1
        st = rec.reset_valve().result(timeout=60)
        assert st.state.name == "IDLE" and st.position.value >= 99.0 and rec.valve_open is True
        assert rec.sim.rig.state().name == "IDLE"
        # new settings go with the arm command; same driver objects (the same connection)
        path = rec.arm(settings=s.with_changes(duration_s=12.0, run_number=2)).result(timeout=60)
        assert rec.devices == devices and rec.settings.duration_s == 12.0
        second = _trigger_when_baseline_is_in(rec)
        assert second.status == "completed" and second.path == path != first.path, (second.status, second.reason)
        assert rec.sim.rig.trigger_count == 2
        # a reset is refused while a run records
        rec.reset_valve().result(timeout=60)
        rec.arm().result(timeout=60)
        with pytest.raises(VelabError, match="cannot reset the valve"):
            rec.reset_valve().result(timeout=30)
        rec.abort("test over").result(timeout=30)
        rec.wait(60)
    run = read_run(second.path)
    assert run.status == "completed" and run.duration_after_trigger_s > 1.9
