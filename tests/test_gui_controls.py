"""GUI wiring against a recorder stand-in (same contract as velab.recording): live plot at 10 kHz,
a refusal raised by the engine's Future and a structured device fault as messages, button states.
The real engine and simulated rig are driven in test_gui_run.py."""

from __future__ import annotations

import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pyqtgraph")

from gui_fakes import FakeRecorder  # noqa: E402

pytestmark = [pytest.mark.gui, pytest.mark.usefixtures("qt_cleanup")]


@pytest.fixture()
def win(qtbot, tmp_path):
    from velab.gui.app import ensure_app
    from velab.gui.main_window import MainWindow, make_settings

    ensure_app()
    made = []

    def factory(**settings):
        r = FakeRecorder(settings)
        made.append(r)
        return r

    w = MainWindow(settings=make_settings(tmp_path / "gui.ini"), recorder_factory=factory)
    w.made = made
    qtbot.addWidget(w)
    w.show()
    yield w
    w.close()


def test_run_through_controls_live_plot(qtbot, win):
    from PySide6.QtCore import Qt

    rp = win.run_panel
    rp.duration_spin.setValue(1.0)
    rp.pre_spin.setValue(0.3)
    rp.rate_combo.setCurrentIndex(rp.rate_combo.findData(10000.0))
    rp.beta_spin.setValue(10.0)
    qtbot.mouseClick(win.devices.reconnect_button, Qt.LeftButton)
    qtbot.waitUntil(lambda: win.controller.phase == "ready", timeout=5000)
    qtbot.waitUntil(lambda: "pressure_adc.head" in win.devices.readings, timeout=5000)
    qtbot.mouseClick(rp.arm_button, Qt.LeftButton)
    qtbot.waitUntil(lambda: rp.trigger_button.isEnabled(), timeout=5000)
    qtbot.waitUntil(lambda: win.live.samples_received > 1000, timeout=5000)
    redraws = win.live.redraws
    qtbot.waitUntil(lambda: win.live.redraws > redraws, timeout=5000)
    qtbot.mouseClick(rp.trigger_button, Qt.LeftButton)
    qtbot.waitUntil(lambda: win.controller.phase == "completed", timeout=10000)
    assert win.live.mode == "whole"
    assert win.live.samples_received == win.made[-1].n >= 13000
    assert win.live.trigger_time_s == 0.0
    assert rp.arm_button.isEnabled() and not rp.trigger_button.isEnabled()
    assert any("Run completed" in t for t in win.log.texts())


def test_engine_refusal_is_a_message(qtbot, win):
    """The engine's SafetyError (a Future's exception) is shown the same way."""
    win.run_panel.beta_spin.setValue(80.0)
    win.controller.arm(win.run_panel.settings())  # bypass the window's own pre-check
    qtbot.waitUntil(lambda: bool(win.log.texts("error")), timeout=5000)
    assert win.log.texts("error")[-1].startswith("Refused by the interlock: closure rate 80")
    assert "Traceback" not in win.log.toPlainText()


def test_device_fault_is_a_message(qtbot, win):
    win.controller.connect_devices(win.run_panel.settings())
    qtbot.waitUntil(lambda: win.controller.phase == "ready", timeout=5000)
    win.made[-1].inject_fault("flowmeter", "no response (timeout)")
    qtbot.waitUntil(lambda: bool(win.log.texts("error")), timeout=5000)
    assert "flowmeter" in win.log.texts("error")[-1] and "no response" in win.banner.text()
    assert "flowmeter" in win.devices.faults
