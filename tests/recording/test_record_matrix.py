"""The fault table of docs/recording.md, run scenario by scenario against the simulated rig.

Every scenario records from real simulated devices (Modbus TCP / RTU over sockets, the
streaming ADC's serial protocol over a socket) on the fast clock (12 x real time), switches a
fault on at one instant of the run (before arm, at arm, at trigger, mid-record) through the
simulators' run-time fault objects, and checks the documented outcome: the run ends (a
deadline, never a hang), with the status of the table (never a plain "completed"), the file
closed and readable with the same status, a fault naming the device, the valve never left
armed, and no traceback from any engine thread.
"""

from __future__ import annotations

import dataclasses
import threading
import time

import pytest

from record_helpers import ABORTED, CWF, DEADLINE_S, FAILED, thread_errors  # noqa: F401 - a fixture
from velab.errors import VelabError
from velab.recording import Recorder, RecordSettings
from velab.runfiles.reader import read_run
from velab.simulators.bench import SimulatedBench
from velab.simulators.clock import make_clock

pytestmark = pytest.mark.slow  # the integration layer: the simulated bench (tests/recording: the stages alone)

REFUSED = "refused"  # arm raises RunRefused (3) or DeviceFailure (5): nothing moved

# (source, target, fault, instant, expected statuses)
MODBUS_PERSISTENT = ("timeout", "exception", "garbled", "silent")
SCENARIOS = []
for target in ("pressure_adc", "valve", "flowmeter"):
    src = "pressure_adc" if target == "pressure_adc" else "streaming_adc"
    for fault in MODBUS_PERSISTENT:
        SCENARIOS.append((src, target, fault, "before_arm", {REFUSED}))
    for fault in ("timeout", "exception", "silent"):
        at_arm = {"pressure_adc": {FAILED}, "valve": {FAILED}, "flowmeter": {CWF}}[target]
        mid = {"pressure_adc": {FAILED}, "valve": {CWF}, "flowmeter": {CWF}}[target]
        SCENARIOS.append((src, target, fault, "at_arm", at_arm))
        SCENARIOS.append((src, target, fault, "mid_record", mid))
    SCENARIOS.append((src, target, "outage", "mid_record", {CWF}))  # disconnect, reconnect OUTAGE_S later
    SCENARIOS.append((src, target, "silent", "at_trigger", {FAILED} if target == "pressure_adc" else {CWF}))
SCENARIOS.append(("streaming_adc", "streaming_adc", "silent", "before_arm", {REFUSED}))
for instant in ("at_arm", "mid_record"):
    SCENARIOS += [
        ("streaming_adc", "streaming_adc", "silent", instant, {FAILED}),
        ("streaming_adc", "streaming_adc", "link_lost", instant, {FAILED}),
        ("streaming_adc", "streaming_adc", "link_back", instant, {CWF}),
        ("streaming_adc", "streaming_adc", "corrupt", instant, {CWF}),
    ]
SCENARIOS.append(("streaming_adc", "streaming_adc", "silent", "at_trigger", {FAILED}))
# sensor faults of the pressure transducer (stuck, 2 mA, 22 mA, NaN, implausible replies), both sources, before
# and after the trigger: tests/recording/test_record_quality.py, scheduled from a sim config
SCENARIOS.append(("streaming_adc", "position_feedback", "stuck", "at_arm", {CWF}))
SCENARIOS.append(("pressure_adc", "position_feedback", "stuck", "at_arm", {CWF}))
# planned before arm (the simulated actuator plans its stroke when armed): it seizes 0.08 s into the stroke
SCENARIOS.append(("streaming_adc", "valve", "seized", "before_arm", {ABORTED}))
SCENARIOS.append(("streaming_adc", "flowmeter", "flow_nan", "mid_record", {CWF}))
SCENARIOS.append(("streaming_adc", "flowmeter", "flow_alarm", "mid_record", {CWF}))  # empty-pipe alarm

DEVICE_OF = {"position_feedback": "valve"}
# Faults of the valve and the flowmeter reach the run only through the slow channels' polls (one every
# velab.recording.slow.POLL_S of host time; a poll of a device that does not answer takes its retries, about
# 1.5 s). A 3 s record is 0.25 s of host time on the fast clock: a starved host can let it end before a poll
# starts after the fault, and the run is rightly "completed" (nothing recorded was bad). Their records are
# long enough in host time for several polls after the fault.
SLOW_TARGETS = ("valve", "flowmeter")
SLOW_DURATION_S = 12.0  # device seconds: 1 s of host time at 12 x
# a fault of theirs switched on after the trigger: the rest of a 12 s record (0.93 s of host time) was less than
# a silent device's retries under two suites at once ("completed", no fault: flowmeter-timeout-mid_record); 3 s of
# host time after it (and for a pressure source's fault mid-record, below)
AFTER_TRIGGER_DURATION_S = 36.0
STALL_S = 1.5  # the runs' stall timeout (wall seconds without pressure samples -> failed)
# a pressure ADC outage shorter than the stall timeout is survived (C-F); one as long is a lost device: the
# outage must stay well inside it (reconnecting and the first read take a timeout or two), or it is a race
OUTAGE_S = STALL_S / 2


def _later(dt, fn):
    t = threading.Timer(dt, fn)
    t.daemon = True
    t.start()


def inject(sim, rec, target: str, fault: str) -> None:
    """Switch one fault on now, through the simulators' run-time fault objects."""
    rf = sim.rig.faults
    if target in ("pressure_adc", "valve", "flowmeter") and fault in MODBUS_PERSISTENT + ("outage",):
        f = sim.faults[target]
        if fault == "timeout":
            f.set(delay_s=0.75)  # longer than the client's timeout (0.5 s): every attempt times out, the reply comes late
        elif fault == "exception":
            f.set(exception_code=4)
        elif fault == "garbled":
            f.set(garble=True)
        elif fault == "silent":
            f.set(silent=True)
        else:
            sim.handles[target].disconnect()
            _later(OUTAGE_S, sim.handles[target].reconnect)
    elif target == "streaming_adc":
        f = sim.faults["streaming_adc"]
        if fault == "silent":
            f.set(silent_after_frames=0)
        elif fault == "link_lost":
            f.set(reconnect_delay_s=60.0, disconnect_after_frames=0)
        elif fault == "link_back":
            f.set(reconnect_delay_s=0.2, disconnect_after_frames=0)
        elif fault == "corrupt":
            f.set(corrupt_every=5)
    elif target == "position_feedback" and fault == "stuck":
        rf.stuck_channels = {**rf.stuck_channels, 1: sim.clock.now()}
    elif fault == "seized":
        rf.valve_fault_after_s = 0.08
    elif fault == "flow_nan":
        rf.flow_nan = True
    elif fault == "flow_alarm":
        rf.flow_alarm_bits = 1
    else:
        raise AssertionError(f"unknown scenario {target} {fault}")


@pytest.mark.timeout(120)
@pytest.mark.parametrize("source,target,fault,instant,expected", SCENARIOS,
                         ids=[f"{s[0]}-{s[1]}-{s[2]}-{s[3]}" for s in SCENARIOS])
def test_fault_table(tmp_path, thread_errors, source, target, fault, instant, expected):
    sim = SimulatedBench.from_config("default", ephemeral=True, clock=make_clock("fast")).start()
    bench = dataclasses.replace(sim.bench(), recorder={"pressure_source": source})
    # a pressure source's fault mid-record acts on the samples it makes from then on; those of the rest of the record
    # can already be in the socket's buffer (the streaming ADC) or the module's ring, read in one poll (the Modbus
    # ADC), when a loaded host runs the acquisition thread that switches it on (the rest of a 3 s record is 0.21 s
    # of host time, of a 12 s one 0.93 s: pairs of suites had streaming_adc link_lost-mid_record "completed" at
    # 12 s and pressure_adc silent-mid_record "completed-with-faults" at 3 s, the fault in the ADC's stop only):
    # 3 s of host time after it
    duration_s = SLOW_DURATION_S if target in SLOW_TARGETS else 3.0
    if (target in SLOW_TARGETS and instant in ("mid_record", "at_trigger")) or \
            (target in ("streaming_adc", "pressure_adc") and instant == "mid_record"):
        duration_s = AFTER_TRIGGER_DURATION_S
    s = RecordSettings(duration_s=duration_s, pretrigger_s=0.5, fit=False, out_dir=tmp_path, stall_timeout_s=STALL_S)
    rec = Recorder(bench, sim.rig.rig, s, sim=sim, owns_sim=True)
    faults, fired = [], threading.Event()
    trigger_t = []

    def fire():
        if not fired.is_set():
            fired.set()
            inject(sim, rec, target, fault)

    def listen(ev):
        if ev.kind == "fault":
            faults.append(ev.data)
        elif ev.kind == "phase" and ev.data["phase"] == "armed" and instant == "at_arm":
            fire()
        elif ev.kind == "phase" and ev.data["phase"] == "recording":
            trigger_t.append(ev.data["trigger_time_s"])
            if instant == "at_trigger":
                fire()
        elif ev.kind == "samples" and instant == "mid_record" and trigger_t and ev.data["time_s"].size \
                and ev.data["time_s"][-1] > trigger_t[0] + 0.8:
            # a fault object's switch is a few attribute writes: made here, on the acquisition thread, it is on
            # at this block, whatever the host's load (from a thread started here, a loaded host switched it on
            # after the record had ended: "completed-with-faults" for want of a fault); an outage stops a
            # server, which is not the acquisition thread's to wait for
            if fault == "outage":
                threading.Thread(target=fire, daemon=True).start()
            else:
                fire()

    rec.add_listener(listen)
    t0 = time.monotonic()
    try:
        rec.connect().result(timeout=DEADLINE_S)
        if instant == "before_arm":
            fire()
        box = {}

        def run():
            try:
                if instant != "at_arm":
                    box["summary"] = rec.run()
                    return
                # at arm: the fault is switched on as the baseline starts; the trigger goes out only after
                # 1 s more of baseline (device time), so the fault is in the baseline, not after the trigger;
                # a flowmeter's fault is seen by a poll (above): the trigger waits for it
                rec.arm().result(timeout=DEADLINE_S)
                start = rec.current_run.timeline.baseline_s
                end = time.monotonic() + DEADLINE_S
                while (rec.current_run.timeline.baseline_s < start + 1.0
                       or (target == "flowmeter" and not any(f["device"] == target for f in faults))) \
                        and rec.phase in ("armed", "triggerable") and time.monotonic() < end:
                    time.sleep(0.005)
                try:
                    rec.trigger().result(timeout=DEADLINE_S)
                except VelabError:
                    pass  # the run already ended (the fault ended it): the summary says how
                box["summary"] = rec.wait(DEADLINE_S)
            except VelabError as exc:
                box["error"] = exc
        th = threading.Thread(target=run, daemon=True)
        th.start()
        th.join(DEADLINE_S)
        assert not th.is_alive(), f"no outcome within {DEADLINE_S} s (phase {rec.phase})"
        elapsed = time.monotonic() - t0
        valve_state, triggers = sim.rig.state().name, sim.rig.trigger_count
    finally:
        sim.faults.get("streaming_adc") and sim.faults["streaming_adc"].set(silent_after_frames=None,
                                                                           disconnect_after_frames=None)
        for n, f in sim.faults.items():
            if hasattr(f, "clear"):
                f.clear()
        closer = threading.Thread(target=rec.close, daemon=True)
        closer.start()
        closer.join(DEADLINE_S)
        assert not closer.is_alive(), "close() did not return"
    assert fired.is_set(), "the fault was never switched on"
    assert not thread_errors, thread_errors
    if valve_state == "ARMED":  # only an actuator that refuses every command can stay armed, and it is said
        assert any("could not be commanded to its safe state" in str(f) for f in faults), "the valve was left armed"
    device = DEVICE_OF.get(target, target)
    if "error" in box:
        err = box["error"]
        assert REFUSED in expected, f"run refused/failed to start: {err}"
        assert err.exit_code in (3, 5) and triggers == 0
        assert device is None or device in str(err) or "pressure" in str(err), err
        return
    summary = box["summary"]
    assert summary.status in expected, (summary.status, summary.reason, [str(f) for f in faults])
    assert summary.status != "completed"
    run = read_run(summary.path)  # closed, readable, same verdict
    assert not run.incomplete and run.status == summary.status
    if summary.status in (ABORTED, FAILED):
        assert summary.reason
    named = [f for f in faults if device is None or f["device"] == device]
    assert named or (device and device in summary.reason), [str(f) for f in faults]
    assert any(k == "fault" for _, k, _ in run.events) or summary.status in (ABORTED, FAILED)
    print(f"{source} {target} {fault} {instant}: {summary.status} in {elapsed:.1f} s ({summary.reason[:90]})")
