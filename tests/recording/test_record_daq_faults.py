"""The fault table of docs/recording.md on the benches of products: the DATAQ DI-2108 and the LabJack T7, each
firing the valve by its line, with the SITRANS flowmeter. Each scenario switches one fault of the simulated
device on at one instant of the run (before arm, or at a scan of the run's stream) and checks the documented
outcome: the run ends within the deadline, with the table's status (never a plain "completed"), the file closed
with the same status, a fault naming the device, and no traceback from any engine thread.
"""

from __future__ import annotations

import pytest

from record_helpers import CWF, DEADLINE_S, FAILED, thread_errors  # noqa: F401 - a fixture
from velab.errors import VelabError
from velab.recording import Recorder, RecordSettings
from velab.runfiles.reader import read_run

pytestmark = pytest.mark.slow

REFUSED = "refused"
RATE_HZ = 1000.0
PRETRIGGER_S = 0.5
MID_SCAN = int((PRETRIGGER_S + 1.0) * RATE_HZ)
# the link lost and back: well after the trigger (a TRIGGER sent while the link is down cannot fire the valve: a failed
# run, rightly; at the fast clock a loaded host's trigger came 0.5 s of device time late)
LATE_SCAN = int((PRETRIGGER_S + 2.5) * RATE_HZ)  # a scan of the run's stream 1 s after the trigger (scans count from
# the run's own start: the readiness look before it is a stream of its own, 50 ms long)


def _dataq(sim, fault):
    f = sim.faults["daq"]
    {"silent": lambda: f.set(silent=True),
     "stall": lambda: f.set(stall_after_scans=MID_SCAN),
     "overflow": lambda: f.set(overflow_after_scans=MID_SCAN),
     "dropped_byte": lambda: f.set(drop_byte_at_scans={MID_SCAN}),
     "link_back": lambda: f.set(disconnect_after_scans=LATE_SCAN, reconnect_delay_s=0.2)}[fault]()


def _labjack(sim, fault):
    h = sim.handles["daq"]
    {"silent": lambda: h.faults.set(silent=True),
     "exception": lambda: h.faults.set(exception_code=4)}[fault]()


def _labjack_at_trigger(sim, fault):
    """The T7's stream faults, switched on as the recording phase starts (the trigger)."""
    sf = sim.handles["daq"].stream_faults
    if fault == "stream_stall":
        sf.stall = True
    elif fault == "scan_overlap":
        sf.scan_overlap = True


# (sim config, target, fault, expected statuses); the DAQ's stream faults are planned before arm at a scan of the
# run's stream (the device counts them), the Modbus ones act from the instant they are set
SCENARIOS = [
    ("dataq", "daq", "silent", {REFUSED}),
    ("dataq", "daq", "stall", {FAILED}),
    ("dataq", "daq", "overflow", {FAILED}),
    ("dataq", "daq", "dropped_byte", {CWF}),
    ("dataq", "daq", "link_back", {CWF}),
    ("dataq", "flowmeter", "silent", {REFUSED}),
    ("labjack", "daq", "silent", {REFUSED}),
    ("labjack", "daq", "exception", {REFUSED}),
    ("labjack", "flowmeter", "silent", {REFUSED}),
    ("labjack", "daq", "stream_stall", {FAILED}),
    ("labjack", "daq", "scan_overlap", {FAILED}),
]
AT_TRIGGER = ("stream_stall", "scan_overlap")


@pytest.mark.timeout(120)
@pytest.mark.parametrize("config,target,fault,expected", SCENARIOS, ids=[f"{s[0]}-{s[1]}-{s[2]}" for s in SCENARIOS])
def test_fault_table_on_the_daq_benches(tmp_path, thread_errors, config, target, fault, expected):
    s = RecordSettings(duration_s=6.0 if fault == "link_back" else 4.0, pretrigger_s=PRETRIGGER_S, fit=False, out_dir=tmp_path, stall_timeout_s=1.5,
                       sample_rate_hz=RATE_HZ)
    with Recorder.simulated(s, config, clock="fast") as rec:
        rec.connect().result(timeout=DEADLINE_S)
        sim = rec.sim
        if target == "flowmeter":
            sim.faults["flowmeter"].set(silent=True)
        elif fault not in AT_TRIGGER:
            (_dataq if config == "dataq" else _labjack)(sim, fault)
        faults = []

        def listen(ev):
            if ev.kind == "fault":
                faults.append(ev.data)
            elif ev.kind == "phase" and ev.data["phase"] == "recording" and fault in AT_TRIGGER:
                _labjack_at_trigger(sim, fault)

        rec.add_listener(listen)
        try:
            summary = rec.run()
        except VelabError as exc:  # refused (3) or a device failure at arm (5): nothing moved, no run recorded
            assert REFUSED in expected, (config, target, fault, str(exc))
            assert exc.exit_code in (3, 5), exc
            assert target in str(exc) or target == "daq" and "daq" in str(exc), str(exc)
            assert sim.rig.trigger_count == 0  # the valve never fired
            if fault == "exception":  # the device answered: it refused (issue 52: named for what happened)
                assert "refused" in str(exc) and "does not answer" not in str(exc), str(exc)
            return
    assert summary.status in expected, (summary.status, summary.reason)
    assert summary.status != "completed"
    run = read_run(summary.path)
    assert run.status == summary.status
    assert any(f.get("device") == target for f in faults) or target in summary.reason, (faults, summary.reason)
