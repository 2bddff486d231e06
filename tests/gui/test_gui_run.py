"""Runs through the window with the real recorder engine and the in-process simulated rig: Stop and
Abort pressed as soon as they are enabled in each phase, the armed timeout, a second run on the same
connection (Reopen + Arm, Reset valve), the interlock's refusal and a device fault as messages.
Each run's file is checked. Helpers: tests/gui_operator.py."""

from __future__ import annotations

import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pyqtgraph")

from gui_operator import Operator, StallProbe, make_window, run_file, stall_limit_s  # noqa: E402

# velab's own bench (the servo actuator): these tests read its simulated actuator's state and trigger count (a fired
# valve's ARMED is the host's own; the window on the DATAQ bench: test_gui_operator.py, test_gui_screens.py)
SERVO = "default"

pytestmark = [pytest.mark.slow, pytest.mark.gui, pytest.mark.usefixtures("qt_cleanup")]  # the integration layer: the simulated bench (tests/recording: the stages alone)


# (phase to press in, window settings that make the phase last long enough to be seen at each clock)
PHASES = {
    "fast": {
        "armed": dict(pre=40.0, duration=2.5),  # 40 s of baseline: 3.3 s of wall time
        "triggerable": dict(pre=0.5, duration=2.5),  # no trigger pressed: triggerable until the armed timeout
        "recording": dict(pre=0.5, duration=60.0, fit_window=20.0),  # 60 s after the trigger: 5 s of wall time
    },
    "realtime": {
        "armed": dict(pre=3.0, duration=2.5),
        "triggerable": dict(pre=0.5, duration=2.5),
        "recording": dict(pre=0.5, duration=5.0, fit_window=4.0),
    },
}
CASES = [("fast", ph, act) for ph in PHASES["fast"] for act in ("stop", "abort")] + [
    ("realtime", "armed", "abort"), ("realtime", "triggerable", "stop"), ("realtime", "recording", "abort")]


@pytest.mark.parametrize("clock,phase,action", CASES)
def test_stop_and_abort_in_every_phase(qtbot, tmp_path, clock, phase, action):
    win = make_window(qtbot, tmp_path, sim_config=SERVO, clock=clock, **PHASES[clock][phase])
    op = Operator(qtbot, win)
    probe = StallProbe().start()
    op.press_when_enabled("connect", 60)
    op.press_when_enabled("arm", 60)
    if phase == "recording":
        op.press_when_enabled("trigger", 60)
    assert op.press_when_enabled(action, 60, phase=phase) == phase
    summary = op.wait_done(60)
    assert probe.stop() < stall_limit_s()
    status, reason, best, run = run_file(summary.path)
    expected = {"stop": ("stopped", "stopped by the operator"), "abort": ("aborted", "operator abort")}[action]
    assert (summary.status, status) == (expected[0], expected[0]) and expected[1] in reason
    # no fit, and why: the run ended before the trigger or before the fit window closed
    assert best is None and summary.fit is None
    assert summary.fit_error.startswith("no fit: the run") if action == "stop" else summary.fit_error
    rig = win.controller.recorder.sim.rig
    assert rig.trigger_count == (1 if phase == "recording" else 0)
    assert rig.state().name != "ARMED"  # the valve is never left armed
    # what the window showed: the engine's allowed commands, nothing else
    assert op.shown_while("fitting") == set()
    assert "trigger" not in op.shown_while("recording") and "arm" not in op.shown_while(phase)
    assert {action} <= op.shown_while(phase)
    assert not win.log.texts("error") or action == "abort"  # an abort is reported as an error line
    assert not any("not possible now" in t for t in win.log.texts())


def test_armed_rig_left_alone_disarms_at_the_configured_time(qtbot, tmp_path):
    """The armed timeout (here 3 s, set in the form) disarms the rig; the window counts it down and
    says why the run ended; the run file says it too and keeps a bounded baseline."""
    win = make_window(qtbot, tmp_path, sim_config=SERVO, clock="realtime", pre=0.5, armed_timeout=3.0, rate=1000.0)
    op = Operator(qtbot, win)
    probe = StallProbe().start()
    op.press_when_enabled("connect", 60)
    op.press_when_enabled("arm", 60)
    qtbot.waitUntil(lambda: "disarms in" in win.run_controls.phase_text(), timeout=10000)
    summary = op.wait_done(60)
    assert probe.stop() < stall_limit_s()
    assert summary.status == "aborted" and summary.reason.startswith("armed timeout: no trigger within 3 s")
    status, reason, best, run = run_file(summary.path)
    assert status == "aborted" and reason.startswith("armed timeout") and best is None
    assert any(k == "disarmed" for _, k, _ in run.events)
    # the baseline kept is bounded by the timeout: the disarm at 3 s of baseline, then the samples that arrive
    # until the stream is stopped (about 0.1 s alone, 0.2 s under two suites at once: a second's margin)
    assert run.n_samples <= int((3.0 + 1.0) * 1000)
    assert run.n_samples >= int(2.5 * 1000)
    assert win.controller.recorder.sim.rig.trigger_count == 0
    assert win.controller.recorder.sim.rig.state().name != "ARMED"
    countdowns = [st.disarm_in() for st in op.states if st.phase in ("armed", "triggerable")]
    countdowns = [c for c in countdowns if c is not None]
    assert countdowns and max(countdowns) <= 3.0 and min(countdowns) < 1.5  # it counted down on screen
    assert any(t.startswith("Disarmed — armed timeout") for t in win.log.texts("warning"))
    assert win.run_controls.phase_label.text() == "aborted" and "armed timeout" in win.run_controls.phase_text()
    assert win.run_controls.arm_button.isEnabled()  # the valve is still open: a new run can be armed


def test_second_run_on_the_same_connection(qtbot, tmp_path):
    """After a completed run the valve is closed: Arm becomes "Reopen + Arm" and carries both out on
    the same Recorder; Reset valve alone reopens it too; the measured trigger reaches the plot."""
    win = make_window(qtbot, tmp_path, sim_config=SERVO, clock="fast", fit=False)
    op = Operator(qtbot, win)
    marks = []
    win.controller.trigger_time.connect(lambda t, measured: marks.append((t, measured, win.last_summary is None)))

    def one_run():
        win.last_summary = None
        op.press_when_enabled("arm", 60)
        op.press_when_enabled("trigger", 60)
        return op.wait_done(90)

    op.press_when_enabled("connect", 60)
    first = one_run()
    rec = win.controller.recorder
    assert first.status == "completed" and first.fit_error == "", (first.status, first.reason)
    measured = [m for m in marks if m[1]]
    assert measured and measured[0][2] and measured[0][0] == first.trigger_time_s  # during the run
    assert win.live.offset_s == first.trigger_time_s
    qtbot.waitUntil(lambda: win.run_controls.arm_button.text() == "Reopen + Arm", timeout=10000)
    assert win.run_controls.reset_valve_button.isEnabled() and win.reset_valve_action.isEnabled()
    second = one_run()
    assert second.status == "completed", (second.status, second.reason)
    assert win.controller.recorder is rec and second.path != first.path
    assert rec.sim.rig.trigger_count == 2
    assert any("reopening it before arming" in t for t in win.log.texts())
    op.press_when_enabled("reset_valve", 30)
    qtbot.waitUntil(lambda: any(t.startswith("Valve reopened") for t in win.log.texts()), timeout=30000)
    qtbot.waitUntil(lambda: win.run_controls.arm_button.text() == "Arm", timeout=10000)
    assert rec.sim.rig.state().name == "IDLE"
    assert not win.log.texts("error") and not win.log.texts("warning")


def test_arm_without_connect_connects_and_arms(qtbot, tmp_path):
    """Arm is enabled before any connection (the engine connects first): one press, one armed run."""
    win = make_window(qtbot, tmp_path, sim_config=SERVO, clock="fast")
    op = Operator(qtbot, win)
    assert win.run_controls.arm_button.isEnabled() and win.controller.recorder is None
    op.press_when_enabled("arm", 60)
    op.press_when_enabled("trigger", 60)
    summary = op.wait_done(90)
    assert summary.status == "completed" and summary.fit is not None, (summary.status, summary.reason)
    assert [p for p, _ in op.presses] == ["arm", "trigger"] and win.controller.recorder.devices
    assert not win.log.texts("error") and not win.log.texts("warning")


def test_interlock_refusal_is_a_message(qtbot, tmp_path):
    from pathlib import Path

    win = make_window(qtbot, tmp_path, sim_config=SERVO, clock="fast")
    rp = win.run_panel
    rp.margin_spin.setValue(50)  # Joukowsky surge + 50 % exceeds the transducer's full scale
    assert "REFUSED" in rp.prediction.text()
    # Arm is not offered when the interlock will refuse (issue 50), and the phase line says why
    qtbot.waitUntil(lambda: win.controller.state.refused != "", timeout=5000)
    assert "EXCEEDS the transducer full scale" in win.controller.state.refused
    assert not win.run_controls.arm_button.isEnabled()
    assert "the interlock refuses these settings" in win.run_controls.phase_text().lower()
    win.arm()  # the window's own Arm (File menu, a test) refuses before touching anything
    msg = win.log.texts("error")[-1]
    assert msg.startswith("Refused by the interlock") and "EXCEEDS the transducer full scale" in msg
    assert "Refused by the interlock" in win.banner.text()
    # the engine refuses on its own too (a SafetyError through the arm Future), for a window that did not know
    win.controller.set_refusal("")
    win.controller.arm(rp.settings())
    qtbot.waitUntil(lambda: len(win.log.texts("error")) >= 2, timeout=60000)
    assert "manoeuvre refused" in win.log.texts("error")[-1]
    assert "Traceback" not in win.log.toPlainText()
    assert not list(Path(rp.settings()["out_dir"]).glob("*.h5"))
    rp.margin_spin.setValue(10)  # a margin the interlock allows: Arm is offered again, nothing is stuck
    qtbot.waitUntil(lambda: win.run_controls.arm_button.isEnabled(), timeout=10000)


def test_device_fault_is_a_message(qtbot, tmp_path):
    win = make_window(qtbot, tmp_path, sim_config=SERVO, clock="fast", pre=30.0, duration=60.0, fit_window=20.0)
    op = Operator(qtbot, win)
    op.press_when_enabled("arm", 60)
    qtbot.waitUntil(lambda: win.controller.phase == "armed", timeout=60000)
    # what the banner showed (a later message may replace it: a loaded host's streaming ADC lost samples)
    shown, show = [], win.banner.show_message
    win.banner.show_message = lambda text, level="info": (shown.append(text), show(text, level))[-1]
    win.controller.recorder.sim.faults["flowmeter"].silent = True
    qtbot.waitUntil(lambda: any("flowmeter" in t for t in win.log.texts("error")), timeout=30000)
    text = [t for t in win.log.texts("error") if "flowmeter" in t][-1]
    assert text.startswith("Device fault") and any("flowmeter" in t for t in shown), shown
    assert "flowmeter" in win.devices.faults
    win.controller.recorder.sim.faults["flowmeter"].silent = False
    op.press_when_enabled("abort", 10)
    summary = op.wait_done(60)
    assert summary.status == "aborted"
