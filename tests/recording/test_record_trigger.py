"""The TRIGGER at its instant, against the simulated actuator over Modbus TCP and RTU (a pty).

A lost reply is realistic here: the simulated actuator carries the command out and the reply is
lost on its way back (``drop_reply``), or the request is lost on its way (``drop_request``: the
valve never moves), or the actuator dies at the trigger (it closes, nobody hears). The recorder
takes the valve driver's named outcome (its read-back decides) and ends as docs/recording.md
says: started -> the run goes on (a fault event says the reply was lost and what was read back);
not started or refused -> failed, the armed valve aborted; unknown -> failed, ABORT sent without
asking, the valve named. Each with a deadline; none hangs or ends "completed".
"""

from __future__ import annotations

import re

import pytest

from record_helpers import CWF, FAILED, fast_sim, recorder, run_bounded, short_settings, thread_errors  # noqa: F401
from velab.runfiles.reader import read_run

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]  # the integration layer: the simulated bench (tests/recording: the stages alone)
TRANSPORTS = {"tcp": None, "rtu": ("rtu-pty", "socket", "tcp")}  # the valve's endpoint (bench preference)


def _run(tmp_path, transport, schedule):
    sim = fast_sim()
    for kw in schedule:
        sim.schedule_fault("valve", **kw)
    rec = recorder(sim, short_settings(tmp_path, duration_s=1.5), prefer=TRANSPORTS[transport])
    assert rec.bench.devices["valve"].settings.get("transport") == ("rtu" if transport == "rtu" else "tcp")
    faults: list = []
    out = run_bounded(rec, faults)
    return out, faults


def _common(out, faults, thread_errors):
    assert not thread_errors, thread_errors
    assert out.error is None, out.error  # the run started: rec.run() returns its summary however it ended
    s = out.summary
    assert s.status != "completed"
    run = read_run(s.path)
    assert not run.incomplete and run.status == s.status
    assert any(f["device"] == "valve" for f in faults), [str(f) for f in faults]
    return run


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_trigger_reply_lost_but_carried_out_runs_on(tmp_path, thread_errors, transport):
    """The actuator executes TRIGGER, its reply is lost: read back RUNNING -> the run goes on."""
    out, faults = _run(tmp_path, transport, [{"at": "trigger", "drop_reply": True, "count": 1}])
    run = _common(out, faults, thread_errors)
    assert out.summary.status == CWF, (out.summary.status, out.summary.reason)
    assert out.triggers == 1 and out.valve_state == "DONE"  # the manoeuvre ran to its end
    lost = [f for f in faults if f["device"] == "valve" and f["kind"] == "protocol"]
    assert lost and re.search(r"TRIGGER reply lost .*; state read back: (RUNNING|DONE), trigger count 1: the "
                              r"manoeuvre started", lost[0]["message"]), lost
    assert any("TRIGGER reply lost" in m for _, k, m in run.events if k == "fault")
    assert out.summary.trigger_time_s is not None and run.trigger_time_s == pytest.approx(out.summary.trigger_time_s)


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_trigger_request_lost_fails_with_the_valve_safe(tmp_path, thread_errors, transport):
    """TRIGGER never reaches the actuator (the valve never moves): read back ARMED -> failed, aborted."""
    out, faults = _run(tmp_path, transport, [{"at": "arm", "drop_request": True, "writes_only": True, "count": 1}])
    _common(out, faults, thread_errors)
    assert out.triggers == 0 and out.valve_state == "ABORTED"  # the armed manoeuvre was cancelled
    assert out.summary.status == FAILED and "trigger not started" in out.summary.reason
    assert out.summary.reason.startswith("valve: ") and "read back: not started" in out.summary.reason


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_trigger_refused_fails_with_the_valve_safe(tmp_path, thread_errors, transport):
    """The actuator answers TRIGGER with an exception (4, device failure): not started -> failed, aborted."""
    out, faults = _run(tmp_path, transport, [{"at": "arm", "exception_code": 4, "writes_only": True, "count": 1}])
    _common(out, faults, thread_errors)
    assert out.triggers == 0 and out.valve_state == "ABORTED"
    assert out.summary.status == FAILED and "TRIGGER refused" in out.summary.reason


@pytest.mark.parametrize("transport,death", [("tcp", "disconnect"), ("rtu", "silent"), ("tcp", "silent")])
def test_valve_dies_at_the_trigger_fails_naming_it(tmp_path, thread_errors, transport, death):
    """The actuator executes TRIGGER and dies before its reply (for good): no read-back -> unknown:
    failed, ABORT commanded without asking (it cannot be reached: said), the valve named."""
    out, faults = _run(tmp_path, transport, [{"at": "trigger", death: True}])
    run = _common(out, faults, thread_errors)
    print(f"ended in {out.elapsed_s:.1f} s: {out.summary.reason}")
    assert out.triggers == 1  # it did start closing
    assert out.summary.status == FAILED
    assert "trigger outcome unknown" in out.summary.reason and out.summary.reason.startswith("valve: ")
    assert any("could not be commanded to its safe state" in f["message"] for f in faults if f["device"] == "valve")
    assert any("abort commanded (state unknown)" in m or "safe state" in m for _, _, m in run.events)
