"""The engine's phases: allowed commands, the queued trigger, the armed timeout, the fit-or-reason
rule, self-describing run files, and `velab record`'s option checks (simulated rig, fast clock)."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import h5py
import pytest

from record_helpers import cli, rate_clock
from velab.errors import VelabError
from velab.recording import Recorder, RecorderEvent, RecordSettings
from velab.runfiles.layout import read_json
from velab.runfiles.reader import read_run
from velab.simulators.bench import SimulatedBench
from velab.simulators.clock import make_clock

pytestmark = pytest.mark.slow  # the integration layer: the simulated bench (tests/recording: the stages alone)

CLI = [sys.executable, "-m", "velab.cli"]


def _phases(events):
    return [e.data["phase"] for e in events if e.kind == "phase"]


@pytest.mark.timeout(120)
def test_trigger_pressed_at_once_is_queued_and_carried_out(tmp_path):
    # a 12 s baseline is 1 s of host time at the fast clock: longer than arming's return takes on a loaded host
    s = RecordSettings(duration_s=2.0, pretrigger_s=12.0, fit=False, out_dir=tmp_path)
    with Recorder.simulated(s, clock="fast") as rec:
        events = []
        rec.add_listener(events.append)
        assert "arm" in rec.allowed_commands() and "trigger" not in rec.allowed_commands()
        rec.connect().result(timeout=60)
        assert rec.phase == "ready" and set(rec.allowed_commands()) >= {"arm", "connect", "reset_valve"}
        rec.arm().result(timeout=60)
        assert rec.phase == "armed" and "trigger" in rec.allowed_commands()
        fut = rec.trigger()  # the baseline is still filling: queued, not refused
        t_trigger = fut.result(timeout=60)
        summary = rec.wait(60)
        assert "trigger" not in rec.allowed_commands() and "reset_valve" in rec.allowed_commands()
        assert "arm" not in rec.allowed_commands()  # the manoeuvre closed the valve: reset first
    queued = [e.data for e in events if e.kind == "trigger" and e.data.get("queued")]
    assert len(queued) == 1 and queued[0]["baseline_remaining_s"] > 0
    assert summary.status == "completed" and rec.sim is None, (summary.status, summary.reason)
    # carried out once the baseline was in, never before (t = 0 is the planned trigger), and not a baseline later
    # (a trigger that waited for a second baseline would be): the baseline is 1 s of host time at the fast clock,
    # room for a loaded host's thread wake-ups and the TRIGGER's round trip (measured: 45 ms under two suites,
    # 0.54 s of device time; 0.69 s of host time, 8.3 s of device time, under two suites and a third job)
    assert 0.0 <= t_trigger < s.pretrigger_s
    ph = _phases(events)
    assert ph.index("armed") < ph.index("triggerable") < ph.index("recording") < ph.index("completed")
    run = read_run(summary.path)
    written = [m for _, k, m in run.events if k == "phase"]
    assert [w.split()[0] for w in written] == ["armed", "armed", "triggerable", "recording", "completed"]
    assert any(k == "operator" and "trigger queued" in m for _, k, m in run.events)


@pytest.mark.timeout(120)
def test_queued_trigger_is_cancelled_with_the_run(tmp_path):
    s = RecordSettings(duration_s=2.0, pretrigger_s=30.0, fit=False, out_dir=tmp_path)
    with Recorder.simulated(s, clock="fast") as rec:
        rec.arm().result(timeout=60)
        fut = rec.trigger()
        rec.stop().result(timeout=30)
        with pytest.raises(VelabError, match="trigger cancelled"):
            fut.result(timeout=30)
        summary = rec.wait(30)
        assert rec.sim.rig.trigger_count == 0 and rec.sim.rig.state().name == "ABORTED"
    assert summary.status == "stopped" and summary.fit_error == ""  # fit=False: no fit expected


@pytest.mark.timeout(120)
def test_armed_rig_left_alone_disarms_itself(tmp_path):
    """The bench's [recorder] armed_timeout_s applies; the run says why it ended, the valve is safe and
    the baseline kept in the file is bounded by the timeout."""
    sim = SimulatedBench.from_config("default", ephemeral=True, clock=make_clock("fast")).start()
    bench = dataclasses.replace(sim.bench(), recorder={"armed_timeout_s": 4.0})
    s = RecordSettings(duration_s=2.0, fit_window_s=2.0, pretrigger_s=1.0, out_dir=tmp_path)
    with Recorder(bench, sim.rig.rig, s, sim=sim, owns_sim=True) as rec:
        events = []
        rec.add_listener(events.append)
        rec.arm().result(timeout=60)
        summary = rec.wait(60)
        assert sim.rig.state().name == "ABORTED" and sim.rig.trigger_count == 0
    assert summary.status == "aborted" and summary.exit_code == 4
    assert summary.reason.startswith("armed timeout") and "disarmed" in summary.reason
    assert "no fit" in summary.fit_error and "before the trigger" in summary.fit_error
    # bounded: the timeout (device time), plus what streams in while the stream is being stopped: a block or
    # two, on a loaded host 0.3 s of host time (3.6 s of device time at 12 x); at most 1 s of host time, far
    # short of a recording that went on (the run's duration and the wait's 60 s)
    assert 4.0 * 1000 <= summary.n_samples < (4.0 + 1.0 * sim.clock.scale) * 1000
    run = read_run(summary.path)
    assert run.status == "aborted" and any(k == "disarmed" for _, k, _ in run.events)
    with h5py.File(summary.path, "r") as fh:
        assert read_json(fh["entry/notes"], "settings_json")["armed_timeout_in_force_s"] == 4.0
    assert _phases(events)[-1] == "aborted"


@pytest.mark.timeout(180)
@pytest.mark.parametrize("i", range(3))
def test_duration_equal_to_the_window_always_ends_with_its_fit(tmp_path, i):
    s = RecordSettings(duration_s=3.0, fit_window_s=3.0, pretrigger_s=0.5, fit_models=(1, 3), out_dir=tmp_path)
    with Recorder.simulated(s, clock="fast") as rec:
        summary = rec.run()
    assert summary.status == "completed", (summary.status, summary.reason)
    assert summary.fit is not None, summary.fit_error
    assert summary.fit_latency_s is not None and "online" in read_run(summary.path).fit_names


@pytest.mark.timeout(120)
def test_halt_ends_now_without_a_fit(tmp_path):
    s = RecordSettings(duration_s=20.0, fit_window_s=10.0, pretrigger_s=0.5, fit_models=(1,), out_dir=tmp_path)
    with Recorder.simulated(s, clock="scaled:2") as rec:
        rec.arm().result(timeout=60)
        rec.trigger().result(timeout=60)
        rec.halt()
        summary = rec.wait(30)
        assert rec.sim.rig.state().name in ("HOLDING", "ABORTED", "DONE")
    assert summary.status == "aborted" and summary.reason.startswith("halted")
    assert summary.fit is None and "halted" in summary.fit_error


@pytest.mark.timeout(300)
def test_run_is_self_describing_and_offline_fit_reproduces_the_online_fit(tmp_path):
    # velab's own bench: its servo actuator runs a commanded manoeuvre (beta 10), its streaming ADC has a serial
    rec = subprocess.run(CLI + ["record", "--simulate", "--sim-config", "default", "--fast", "--beta", "10",
                                "--duration", "12", "--window", "12",
                                "--models", "1-3", "--json", "--out-dir", str(tmp_path / "new" / "runs")],
                         capture_output=True, text=True, timeout=240)
    assert rec.returncode == 0, rec.stderr
    doc = json.loads(rec.stdout, parse_constant=lambda c: pytest.fail(f"non-strict JSON constant {c}"))
    online = doc["runs"][0]
    path = online["path"]
    assert "armed" in rec.stderr and "recording" in rec.stderr  # progress on stderr, the phases printed
    with h5py.File(path, "r") as fh:
        rig = read_json(fh["entry/sample"], "rig_json")
        assert float(fh["entry/manoeuvre/beta"][()]) == 10.0 == rig["manoeuvre"]["beta_per_s"]
        inst = fh["entry/instrument"]
        setup, identities = read_json(inst, "device_setup_json"), read_json(inst, "devices_json")
        profiles, bench = read_json(inst, "device_profiles_json"), read_json(inst, "bench_json")
    assert identities["streaming_adc"]["serial"] and identities["valve"]
    assert "[registers.state]" in profiles["valve"]["toml"]
    assert bench["devices"]
    assert {"velab", "numpy", "scipy", "h5py", "pymodbus"} <= set(setup["versions"])
    off = cli(["fit", path, "--window", "12", "--models", "1-3", "--json", "--no-save"])
    assert off.returncode == 0, off.stderr
    offline = json.loads(off.stdout)
    best = offline["best"]
    a = next(m["wave_speed"] for m in offline["models"] if m["name"] == best)
    assert best == online["best_model"]
    assert abs(a - online["wave_speed_m_s"]) < 0.5


def test_record_options_are_checked(tmp_path):
    def rec(*a):
        return cli(["record", "--simulate", "--fast", "--no-fit", "--out-dir", str(tmp_path), *a])
    for bad in (["--ceiling", "inf"], ["--duration", "nan"], ["--rate", "-5"], ["--repeat", "0"]):
        r = rec(*bad)
        assert r.returncode == 2 and "Traceback" not in r.stderr, (bad, r.stderr)
    r = rec("--rate", "1e9", "--duration", "1")  # beyond any rate: refused by the option's domain
    assert r.returncode == 2 and "--rate" in r.stderr and r.stderr.count("\n") == 1
    r = rec("--rate", "2e5", "--duration", "1")  # a rate, but beyond the pressure source's 50 kHz
    assert r.returncode == 2 and "outside the range" in r.stderr and "Traceback" not in r.stderr
    r = rec("--ceiling", "500", "--duration", "1")
    assert r.returncode == 2 and "above the limiting pressure" in r.stderr
    blocked = tmp_path / "file"
    blocked.write_text("x")
    r = cli(["record", "--simulate", "--out-dir", str(blocked / "sub")])
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "--out-dir" in r.stderr


@pytest.mark.timeout(120)
def test_no_phase_event_is_lost_when_nobody_drains_the_events(tmp_path):
    """The bounded event queue drops live samples first: every phase, fault and the summary stay."""
    s = RecordSettings(duration_s=3.0, pretrigger_s=0.5, sample_rate_hz=10000, fit=False, out_dir=tmp_path)
    with Recorder.simulated(s, clock=rate_clock(10000)) as rec:
        for _ in range(rec.events.maxsize):  # a consumer that stopped draining: the queue is full already
            rec.events.put_nowait(RecorderEvent("samples", 0.0, None))
        summary = rec.run()
        evs = []
        while not rec.events.empty():
            evs.append(rec.events.get_nowait())
        assert rec.events_dropped > 0
    phases = [e.data["phase"] for e in evs if e.kind == "phase"]
    assert [p for p in ("ready", "armed", "triggerable", "recording", "completed") if p in phases] == \
        ["ready", "armed", "triggerable", "recording", "completed"], phases
    assert evs[-1].kind == "done" and evs[-1].data is summary
