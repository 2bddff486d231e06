"""GUI against the real recorder engine and the in-process simulated rig (fast clock):
a whole test through the window's controls, the interlock refusal and a device fault."""

from __future__ import annotations

import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pyqtgraph")

pytestmark = [pytest.mark.gui, pytest.mark.usefixtures("qt_cleanup")]


@pytest.fixture()
def win(qtbot, tmp_path):
    from velab.gui.app import ensure_app, recorder_factory
    from velab.gui.main_window import MainWindow, make_settings

    ensure_app()
    factory, rig = recorder_factory(simulate=True, clock="fast", material="A")
    w = MainWindow(settings=make_settings(tmp_path / "gui.ini"), recorder_factory=factory, rig=rig,
                   source_label="simulated rig")
    rp = w.run_panel
    rp.duration_spin.setValue(3.0)
    rp.pre_spin.setValue(0.5)
    rp.fit_window_spin.setValue(2.0)
    rp.models_edit.setText("0-2")
    rp.out_edit.setText(str(tmp_path / "runs"))
    rp.operator_edit.setText("test")
    qtbot.addWidget(w)
    w.show()
    yield w
    w.close()


def test_whole_run_through_the_window(qtbot, win):
    from PySide6.QtCore import Qt

    rp = win.run_panel
    rp.rate_combo.setCurrentIndex(rp.rate_combo.findData(10000.0))
    rp.title_edit.setText("GUI test run")
    assert "within limits" in rp.prediction.text()  # shown before arming
    qtbot.mouseClick(rp.arm_button, Qt.LeftButton)
    qtbot.waitUntil(lambda: win.controller.phase == "triggerable", timeout=60000)
    assert rp.trigger_button.isEnabled() and not rp.arm_button.isEnabled()
    qtbot.waitUntil(lambda: win.live.samples_received > 6000, timeout=30000)  # baseline complete at 10 kHz
    qtbot.waitUntil(lambda: win.live.redraws > 0, timeout=5000)
    qtbot.mouseClick(rp.trigger_button, Qt.LeftButton)
    qtbot.waitUntil(lambda: win.last_summary is not None, timeout=90000)
    s = win.last_summary
    assert s.status == "completed", s
    assert win.live.mode == "whole" and win.live.trigger_time_s is not None
    assert win.live.samples_received == s.n_samples  # every sample reached the live plot
    assert win.live.buffer.column("head_m").max() > 40.0  # the surge is there
    assert "valve_position" in win.devices.readings and "flow" in win.devices.readings
    qtbot.waitUntil(lambda: win.fit_panel.data is not None, timeout=30000)
    assert win.fit_panel.best_name() == s.best_model
    assert win.fit_panel.model_names() == ["EL", "S1", "S2"]
    assert s.path.exists() and rp.arm_button.isEnabled()
    # the finished run is listed in the archive browser
    qtbot.waitUntil(lambda: win.archive.files.count() == 1, timeout=5000)
    assert not win.log.texts("error")


def test_interlock_refusal_is_a_message(qtbot, win):
    from PySide6.QtCore import Qt

    rp = win.run_panel
    rp.margin_spin.setValue(50)  # Joukowsky surge + 50 % exceeds the transducer's full scale
    assert "REFUSED" in rp.prediction.text()
    qtbot.mouseClick(rp.arm_button, Qt.LeftButton)
    msg = win.log.texts("error")[-1]
    assert msg.startswith("Refused by the interlock") and "EXCEEDS the transducer full scale" in msg
    assert "Refused by the interlock" in win.banner.text()
    # the engine refuses on its own too (a SafetyError through the arm Future)
    win.controller.arm(rp.settings())
    qtbot.waitUntil(lambda: len(win.log.texts("error")) >= 2, timeout=60000)
    assert "manoeuvre refused" in win.log.texts("error")[-1]
    assert "Traceback" not in win.log.toPlainText()
    assert not list((win.run_panel.settings()["out_dir"] and __import__("pathlib").Path(rp.settings()["out_dir"])).glob("*.h5"))


def test_device_fault_is_a_message(qtbot, win):
    rp = win.run_panel
    rp.duration_spin.setValue(60.0)
    rp.pre_spin.setValue(30.0)  # stays in the pre-trigger while the flowmeter goes silent
    win.arm()
    qtbot.waitUntil(lambda: win.controller.phase == "triggerable", timeout=60000)
    win.controller.recorder.sim.faults["flowmeter"].silent = True
    qtbot.waitUntil(lambda: any("flowmeter" in t for t in win.log.texts("error")), timeout=30000)
    text = [t for t in win.log.texts("error") if "flowmeter" in t][-1]
    assert text.startswith("Device fault") and "flowmeter" in win.banner.text()
    assert "flowmeter" in win.devices.faults
    win.controller.recorder.sim.faults["flowmeter"].silent = False
    win.controller.abort("test over")
    qtbot.waitUntil(lambda: win.controller.phase == "aborted", timeout=30000)


def test_second_run_on_the_same_connection(qtbot, win):
    """Arm after a completed run re-arms the same Recorder (the valve is reopened first); Reset valve is
    offered while the valve is closed; the trigger marker moves to the measured instant during the run;
    a device fault arrives as structured data."""
    from PySide6.QtCore import Qt

    rp = win.run_panel
    rp.fit_check.setChecked(False)
    marks = []
    win.controller.trigger_time.connect(lambda t, measured: marks.append((t, measured, win.last_summary is None)))
    assert not rp.reset_valve_button.isEnabled()

    def one_run():
        qtbot.mouseClick(rp.arm_button, Qt.LeftButton)
        qtbot.waitUntil(lambda: win.controller.phase == "triggerable", timeout=60000)
        qtbot.waitUntil(lambda: win.live.samples_received > 600, timeout=30000)  # the 0.5 s baseline is in
        qtbot.mouseClick(rp.trigger_button, Qt.LeftButton)
        qtbot.waitUntil(lambda: win.last_summary is not None, timeout=90000)
        return win.last_summary

    first = one_run()
    rec = win.controller.recorder
    assert first.status == "completed"
    # the measured trigger reached the plot while the run was still going on
    measured = [m for m in marks if m[1]]
    assert measured and measured[0][2] and measured[0][0] == first.trigger_time_s
    assert win.live.trigger_time_s == first.trigger_time_s
    qtbot.waitUntil(lambda: rp.reset_valve_button.isEnabled(), timeout=10000)  # the valve is closed
    assert win.reset_valve_action.isEnabled()
    # Arm right away: same recorder, valve reopened, second run
    second = one_run()
    assert win.controller.recorder is rec and second.status == "completed" and second.path != first.path
    assert rec.sim.rig.trigger_count == 2
    assert any("reopening it before arming" in t for t in win.log.texts())
    # the button on its own: reopens the valve and is then disabled
    qtbot.waitUntil(lambda: rp.reset_valve_button.isEnabled(), timeout=10000)
    qtbot.mouseClick(rp.reset_valve_button, Qt.LeftButton)
    qtbot.waitUntil(lambda: any(t.startswith("Valve reopened") for t in win.log.texts()), timeout=30000)
    qtbot.waitUntil(lambda: not rp.reset_valve_button.isEnabled(), timeout=10000)
    assert rec.sim.rig.state().name == "IDLE"
    assert not win.log.texts("error")
