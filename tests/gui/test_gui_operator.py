"""The operator window driven as an operator does (issue 16): each control pressed the moment it is
enabled, with the real recorder engine and the simulated rig at the real and the fast clock; the run
file checked; the GUI thread's stalls measured. Helpers: tests/gui_operator.py."""

from __future__ import annotations

import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pyqtgraph")

from gui_operator import Operator, StallProbe, make_window, run_file, stall_limit_s  # noqa: E402

pytestmark = [pytest.mark.gui, pytest.mark.usefixtures("qt_cleanup")]

# runs per clock: the acceptance's 10 of 10 on the fast clock (the same engine, presses and window, 12 x
# quicker); 4 in real time, where each run costs ~7 s of wall and a final fit
REPEATS = {"fast": 10, "realtime": 4}
# the run's length in device time: at the fast clock (12 x) a 2 s window is 0.17 s of host time, and a loaded host
# (two suites at once) delayed the TRIGGER past it: the stroke came after the window, "no stroke seen"
LENGTHS = {"fast": dict(duration=6.0, fit_window=5.0), "realtime": {}}


def _one_run(qtbot, tmp_path, clock: str) -> dict:
    """Connect, Arm, Trigger: each pressed once, as soon as it is enabled. Returns what happened."""
    from velab.gui.live_plot import AXIS_MEASURED, AXIS_PLANNED

    win = make_window(qtbot, tmp_path, clock=clock, **LENGTHS[clock])
    op = Operator(qtbot, win)
    probe = StallProbe(where=lambda: win.controller.phase).start()
    try:
        op.press_when_enabled("connect", 60)
        op.press_when_enabled("arm", 60)
        trigger_phase = op.press_when_enabled("trigger", 60)
        summary = op.wait_done(120)
        op._axis()  # the label as the run ends (on a loaded host the measured instant can follow the last block)
        # the final fit, read back from the run file, is in the Fit page (drawn when the page is opened)
        qtbot.waitUntil(lambda: win.fit_panel.result is summary.fit and "final fit" in win.fit_panel.title,
                        timeout=60000)
    finally:
        stall = probe.stop()
    status, reason, best, run = run_file(summary.path)
    out = dict(summary=summary, status=status, reason=reason, best=best, stall=stall, trigger_phase=trigger_phase,
               presses=list(op.presses), worst=probe.worst, events=run.events, errors=win.log.texts("error"),
               warnings=win.log.texts("warning"), axis=list(op.axis_labels), op=op,
               offset=win.live.offset_s,
               queued_logged=any(t.startswith("Trigger queued") for t in win.log.texts()))
    # what the window showed in each phase: the buttons follow the engine's allowed commands
    out["shown"] = {ph: op.shown_while(ph) for ph in ("connecting", "ready", "armed", "triggerable", "recording",
                                                       "fitting", "completed")}
    assert op.axis_labels[0] == AXIS_PLANNED and op.axis_labels[-1] == AXIS_MEASURED, op.axis_labels
    win.close()
    return out


@pytest.mark.parametrize("clock", ["realtime", "fast"])
def test_connect_arm_trigger_as_soon_as_enabled_completes_10_of_10(qtbot, tmp_path, clock):
    """Acceptance (issue 16): 10 of 10 runs complete (4 of 4 in real time) with their online fit; no press is lost or refused;
    the GUI thread never blocks (stall_limit_s(); the 250 ms figure is benchmarks/gui_latency.py's)."""
    runs, failures = [], []
    for i in range(REPEATS[clock]):
        r = _one_run(qtbot, tmp_path / f"run{i}", clock)
        runs.append(r)
        s = r["summary"]
        if not (s.status == r["status"] == "completed" and s.fit is not None and r["best"] == s.best_model
                and [p for p, _ in r["presses"]] == ["connect", "arm", "trigger"]
                and not r["errors"] and not r["warnings"] and r["stall"] < stall_limit_s()):
            failures.append(f"run {i}: {s.status} ({s.reason}) fit_error={s.fit_error!r} best={r['best']} "
                            f"presses={r['presses']} errors={r['errors']} warnings={r['warnings']} "
                            f"stall={r['stall']:.3f} s at {r['worst']}")
    assert not failures, "\n".join(failures)
    for r in runs:
        ev = [(k, m) for _, k, m in r["events"]]
        # each press acted: the trigger was commanded once and the run's axis is the measured trigger's
        assert sum(1 for k, m in ev if k == "operator" and m.startswith("trigger commanded")) == 1
        assert r["offset"] == pytest.approx(r["summary"].trigger_time_s)
        # pressed while the baseline filled: queued, shown, carried out. The window's phase lags the
        # engine's by up to a timer tick, so a press shown as "armed" may reach the engine after the
        # baseline is in (at the fast clock the baseline lasts 42 ms): the engine's event log says
        # whether it was queued, and then the window must have said so: its message comes from the engine's
        # event (the control bar's "Trigger queued" state can last less than a tick; the 3 s baseline
        # test below checks it)
        queued = any(k == "operator" and "trigger queued" in m for k, m in ev)
        assert queued <= (r["trigger_phase"] == "armed")  # never queued once the window showed triggerable
        assert queued == r["queued_logged"]
        shown = r["shown"]
        assert shown["connecting"] == set() and shown["fitting"] == set()
        assert shown["recording"] <= {"stop", "abort"} and "trigger" not in shown["recording"]
        assert "arm" not in shown["armed"] | shown["triggerable"] | shown["recording"]
    stalls = sorted(r["stall"] for r in runs)
    print([r["worst"] for r in runs])
    print(f"{clock}: {len(runs)} runs completed; GUI-thread stall max {stalls[-1] * 1e3:.0f} ms, "
          f"median {stalls[len(stalls) // 2] * 1e3:.0f} ms; trigger pressed while "
          f"{sorted({r['trigger_phase'] for r in runs})}")


def test_trigger_pressed_during_the_baseline_is_queued_and_shown(qtbot, tmp_path):
    """At the real clock with a 3 s baseline, Trigger is enabled while armed: the press is queued, the
    window says so with the baseline still to go, and the engine carries it out when the baseline is in."""
    win = make_window(qtbot, tmp_path, clock="realtime", pre=3.0, duration=2.5)
    op = Operator(qtbot, win)
    op.press_when_enabled("connect", 60)
    op.press_when_enabled("arm", 60)
    assert op.press_when_enabled("trigger", 60) == "armed"
    qtbot.waitUntil(lambda: "Trigger queued" in win.run_controls.phase_text(), timeout=5000)
    assert not win.run_controls.trigger_button.isEnabled()  # not offered twice
    assert win.run_controls.stop_button.isEnabled() and win.run_controls.abort_button.isEnabled()
    assert "Trigger queued" in win.phase_label.text() or "armed" in win.phase_label.text()
    summary = op.wait_done(120)
    assert summary.status == "completed" and summary.fit is not None, (summary.status, summary.reason)
    queued = [st for st in op.states if st.trigger_queued]
    assert queued and all(st.countdown("baseline") is None or st.countdown("baseline") <= 3.0 for st in queued)
    assert any(t.startswith("Trigger queued: fires when the baseline is in") for t in win.log.texts())


def test_queued_trigger_is_cancelled_with_the_run(qtbot, tmp_path):
    win = make_window(qtbot, tmp_path, clock="fast", pre=40.0, duration=2.5)  # 40 s of baseline: 3.3 s of wall time
    op = Operator(qtbot, win)
    op.press_when_enabled("connect", 60)
    op.press_when_enabled("arm", 60)
    assert op.press_when_enabled("trigger", 60) == "armed"
    qtbot.waitUntil(lambda: "Trigger queued" in win.run_controls.phase_text(), timeout=5000)
    op.press_when_enabled("stop", 10)
    summary = op.wait_done(60)
    assert summary.status == "stopped"
    qtbot.waitUntil(lambda: any("Queued trigger cancelled" in t for t in win.log.texts("warning")), timeout=10000)
    status, reason, best, run = run_file(summary.path)
    assert status == "stopped" and "stopped by the operator" in reason and best is None
    assert any(k == "operator" and "trigger queued" in m for _, k, m in run.events)
    assert not any(k == "operator" and m.startswith("trigger commanded") for _, k, m in run.events)
    assert win.controller.recorder.sim.rig.trigger_count == 0
