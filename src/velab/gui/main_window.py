"""The operator's main window: Run page (control bar, devices, run form, live plot), Fit page,
Archive page, and a message log. The window only reads state and sends commands (controller.py);
what it enables comes from the engine's phase (state.py)."""

from __future__ import annotations

import gc
import time
import traceback
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from PySide6.QtCore import QSettings, Qt, QTimer, Signal
from PySide6.QtGui import QAction, QGuiApplication, QKeySequence
from PySide6.QtWidgets import QDockWidget, QLabel, QMainWindow, QTabWidget

from velab.gui import gcguard, tasks
from velab.gui.archive import ArchiveBrowser
from velab.gui.archive_io import fit_window_of
from velab.gui.controller import RecorderController
from velab.gui.fit_panel import FitPanel
from velab.gui.messages import MessageLog, describe_error
from velab.gui.run_controls import status_text
from velab.gui.run_page import RunPage
from velab.gui.state import COLORS, ControlState
from velab.recording.safety import predict_surge
from velab.recording.settings import RecordSettings

ORG, APP = "velab", "velab-gui"


def make_settings(path=None) -> QSettings:
    """The GUI's persistent settings: an INI file at ``path``, else the user's (org velab, app velab-gui)."""
    if path:
        return QSettings(str(path), QSettings.IniFormat)
    return QSettings(QSettings.IniFormat, QSettings.UserScope, ORG, APP)


def freeze_heap() -> None:
    """Collect, then move every object alive now (modules, Qt wrappers, the window) out of the cyclic
    garbage collector's reach (``gc.freeze``). A full collection of the ~250 000 objects of a running
    window took 65-170 ms with the GIL held, on whichever thread triggered it (the GUI thread, or an
    engine or simulator thread, which the GUI thread then waited for); afterwards a collection scans
    only what was made since (docs/gui.md, "Latency")."""
    gc.collect()
    gc.freeze()


class MainWindow(QMainWindow):
    message_shown = Signal(str, str)

    def __init__(self, *, settings: QSettings | None = None, recorder_factory=None, rig=None,
                 source_label: str = "", parent=None):
        super().__init__(parent)
        self.qs = settings if settings is not None else make_settings()
        self.rig = rig
        self.setWindowTitle("velab — water-hammer bench" + (f" ({source_label})" if source_label else ""))
        self.last_summary = None
        self.last_run_path: Path | None = None

        self.tabs = QTabWidget()
        self.setCentralWidget(self.tabs)
        self.run_page = RunPage(self.qs, rig=rig)
        self.tabs.addTab(self.run_page, "Run")
        # the Run page's parts, by the names the rest of the window (and the tests) use
        self.banner, self.run_controls = self.run_page.banner, self.run_page.controls
        self.devices, self.run_panel, self.live = self.run_page.devices, self.run_page.form, self.run_page.live
        self.run_split = self.run_page.split
        self.fit_panel = FitPanel(title="No fit yet: the fit of each run appears here.")
        self.tabs.addTab(self.fit_panel, "Fit")
        self.archive = ArchiveBrowser(self.qs)
        self.archive.message.connect(self.show_message)
        self.tabs.addTab(self.archive, "Archive")

        self.log = MessageLog()
        dock = QDockWidget("Messages", self)
        dock.setObjectName("messages")
        dock.setWidget(self.log)
        dock.setFeatures(QDockWidget.DockWidgetMovable | QDockWidget.DockWidgetFloatable
                         | QDockWidget.DockWidgetClosable)
        self.addDockWidget(Qt.BottomDockWidgetArea, dock)
        self.resizeDocks([dock], [100], Qt.Vertical)
        self.messages_dock = dock
        self.phase_label = QLabel("disconnected")
        self.phase_label.setMinimumWidth(220)
        self.phase_label.setAlignment(Qt.AlignCenter)
        self.statusBar().addPermanentWidget(self.phase_label)
        self._menus()

        self.controller = None
        if recorder_factory is not None:
            self.controller = c = RecorderController(recorder_factory, self)
            c.state_changed.connect(self._state)
            c.phase_info.connect(self._phase_info)
            c.samples.connect(self.live.append)
            c.devices.connect(self.devices.update_readings)
            c.fit.connect(self._fit_event)
            c.message.connect(self.show_message)
            c.fault.connect(self._fault)
            c.done.connect(self._done)
            c.armed.connect(self._armed)
            c.triggered.connect(self._triggered)
            c.trigger_queued.connect(self._trigger_queued)
            c.trigger_time.connect(self._trigger_time)
            c.valve.connect(self.devices.update_valve)
            c.valve_reset.connect(self._valve_reset)
            self.run_controls.clicked.connect(self._action)
            self.run_panel.changed.connect(self.update_prediction)
            self._state(c.state)
        else:
            self.run_page.setEnabled(False)
            self.devices.set_state("No bench: start with --simulate or --config BENCH.toml to record.")
        self.plot_timer = QTimer(self)
        self.plot_timer.setInterval(100)
        self.plot_timer.timeout.connect(self._refresh_plot)
        self.plot_timer.start()
        self._restore()
        self.update_prediction()
        freeze_heap()  # long-lived objects out of the garbage collector's full scans
        gcguard.acquire()  # collections on this thread only while the window is open (velab.gui.gcguard)
        self._gc_held = True

    # ------------------------------------------------------------------ layout
    def _menus(self) -> None:
        m = self.menuBar().addMenu("&File")
        a = QAction("&Open run…", self)
        a.setShortcut(QKeySequence.Open)
        a.triggered.connect(lambda: (self.tabs.setCurrentWidget(self.archive), self.archive.choose_file()))
        m.addAction(a)
        a = QAction("Runs &folder…", self)
        a.triggered.connect(lambda: (self.tabs.setCurrentWidget(self.archive), self.archive.choose_folder()))
        m.addAction(a)
        m.addSeparator()
        self.reset_valve_action = QAction("&Reset valve", self)
        self.reset_valve_action.setToolTip("reopen the valve (actuator reset) on the current connection")
        self.reset_valve_action.setEnabled(False)
        self.reset_valve_action.triggered.connect(lambda: self._action("reset_valve"))
        m.addAction(self.reset_valve_action)
        m.addSeparator()
        a = QAction("&Quit", self)
        a.setShortcut(QKeySequence.Quit)
        a.triggered.connect(self.close)
        m.addAction(a)
        v = self.menuBar().addMenu("&View")
        v.addAction(self.messages_dock.toggleViewAction())

    def _restore(self) -> None:
        geo = self.qs.value("window/geometry")
        if geo is not None:
            self.restoreGeometry(geo)
        else:
            screen = QGuiApplication.primaryScreen()
            avail = screen.availableGeometry() if screen else None
            w = min(1366, avail.width()) if avail else 1280
            h = min(768, avail.height()) if avail else 720
            self.resize(max(w, 800), max(h, 560))
        state = self.qs.value("window/state")
        if state is not None:
            self.restoreState(state)
        for key, split in (("window/run_split", self.run_split), ("window/archive_split", self.archive.splitter)):
            v = self.qs.value(key)
            if v is not None:
                split.restoreState(v)
        tab = self.qs.value("window/tab")
        if tab is not None:
            self.tabs.setCurrentIndex(int(tab))

    def save_settings(self) -> None:
        self.qs.setValue("window/geometry", self.saveGeometry())
        self.qs.setValue("window/state", self.saveState())
        self.qs.setValue("window/run_split", self.run_split.saveState())
        self.qs.setValue("window/archive_split", self.archive.splitter.saveState())
        self.qs.setValue("window/tab", self.tabs.currentIndex())
        self.run_panel.save()
        self.qs.sync()

    def closeEvent(self, event) -> None:
        self.save_settings()
        if self.controller is not None:
            self.controller.close()
        tasks.wait_idle(5000)
        super().closeEvent(event)
        if getattr(self, "_gc_held", False):
            self._gc_held = False
            gcguard.release()

    # ------------------------------------------------------------------ messages
    def show_message(self, text: str, level: str = "info", details: str = "") -> None:
        """Status bar + message log; warnings and errors also in the banner on the Run page."""
        self.log.add(text, level, details)
        self.statusBar().showMessage(text, 15000 if level == "info" else 0)
        if level in ("warning", "error"):
            self.banner.show_message(text, level)
        self.message_shown.emit(text, level)

    def report_exception(self, exc: BaseException, where: str = "") -> None:
        level, text = describe_error(exc)
        details = getattr(exc, "__velab_traceback__", "") or "".join(
            traceback.format_exception(type(exc), exc, exc.__traceback__))
        internal = text.startswith("Internal error")
        self.show_message((f"{where}: " if where else "") + text, level, details if internal else "")

    # ------------------------------------------------------------------ the run's controls
    def _action(self, name: str) -> None:
        {"connect": self.connect_devices, "arm": self.arm, "trigger": self.trigger, "stop": self.stop,
         "abort": self.abort, "reset_valve": self.reset_valve}[name]()

    def connect_devices(self) -> None:
        self.show_message("Connecting the devices…")
        self.controller.connect_devices(self.run_panel.settings())

    def arm(self) -> None:
        pred = self._predict()
        if isinstance(pred, BaseException):
            self.report_exception(pred, "Cannot arm")
            return
        if pred is not None and not getattr(pred, "allowed", True):
            # the engine refuses too; say it here before touching anything
            self.show_message(f"Refused by the interlock: {getattr(pred, 'message', '') or 'predicted surge over the limit'}",
                              "error")
            self.update_prediction()
            return
        self.banner.hide()
        self.run_panel.save()
        self.last_summary = None
        self.live.clear()  # here, not on the engine's "armed": its samples may already be on their way
        self.fit_panel.clear("Fit of the new run: after the fit window has been recorded.")
        self.show_message("Arming…")
        self.controller.arm(self.run_panel.settings())

    def trigger(self) -> None:
        self.controller.trigger()

    def stop(self) -> None:
        self.controller.stop()

    def abort(self) -> None:
        self.controller.abort("operator abort")

    def reset_valve(self) -> None:
        if self.controller is not None:
            self.controller.reset_valve(self.run_panel.settings())

    def _state(self, st: ControlState) -> None:
        """Every control from the engine's phase and allowed commands (and the window's commands in flight)."""
        self.run_controls.apply(st)
        self.reset_valve_action.setEnabled(st.controls()["reset_valve"])
        self.run_panel.set_phase(st.phase)
        text = status_text(st)
        if text != self.phase_label.text():
            self.phase_label.setText(text)
            # wide enough for its text at once (a countdown that grows by a digit was drawn cut until the status
            # bar's next layout pass), and never narrower again (no jitter while the countdown runs)
            need = self.phase_label.fontMetrics().horizontalAdvance(text) + 24  # (+ the style's padding)
            if need > self.phase_label.minimumWidth():
                self.phase_label.setMinimumWidth(need)
                self.statusBar().layout().activate()
        style = f"background:{COLORS.get(st.indicator()[0], 'transparent')}; padding:2px 6px;"
        if self.phase_label.styleSheet() != style:
            self.phase_label.setStyleSheet(style)

    # ------------------------------------------------------------------ the interlock's prediction
    def _predict(self):
        """The interlock's prediction for the form's settings (pure; the engine checks it again at arm)."""
        if self.controller is None:
            return None
        s = self.run_panel.settings()
        rec = self.controller.recorder
        rig = self.rig or getattr(rec, "rig", None)
        if rig is None:
            return None
        steady = getattr(rec, "_steady", None) if rec is not None else None
        try:
            return predict_surge(rig, RecordSettings(**{k: v for k, v in s.items() if k != "out_dir"}), steady)
        except Exception as exc:  # settings the engine rejects (VelabError): say so in the prediction line
            return exc

    def update_prediction(self) -> None:
        """The interlock's line under the control bar, and Arm offered only when the interlock would allow it."""
        pred = self._predict()
        if isinstance(pred, BaseException):
            why = describe_error(pred)[1]
            self.run_panel.show_settings_error(why)
        else:
            self.run_panel.show_prediction(pred)
            why = "" if pred is None or getattr(pred, "allowed", True) else (
                getattr(pred, "message", "") or "predicted surge over the limit")
        if self.controller is not None:
            self.controller.set_refusal(why)

    # ------------------------------------------------------------------ engine events
    def _devices_ready(self, devices: list) -> None:
        """The engine's ``ready`` phase lists the devices that answered (after Connect, or Arm connecting)."""
        self.devices.update_status([SimpleNamespace(**d) for d in devices])
        # a valve fired by a digital line makes its own stroke: the form's manoeuvre is not a command to it
        self.run_panel.set_fired_valve(any(d.get("role") == "valve" and d.get("kind") == "fired_valve" for d in devices))
        self.update_prediction()
        self.show_message("Devices connected: " + ", ".join(f"{d['name']} ({d['role']})" for d in devices) + ".")

    def _armed(self, path) -> None:
        self.last_run_path = Path(path) if path else None
        self.show_message(f"Armed: recording to {path}. Trigger closes the valve once the baseline is in.")

    def _valve_reset(self, st) -> None:
        state = getattr(getattr(st, "state", None), "name", "")
        pos = getattr(getattr(st, "position", None), "value", None)
        self.show_message("Valve reopened" + (f": actuator {state}" if state else "")
                          + (f", {pos:.1f} % open" if isinstance(pos, (int, float)) else "") + ".")

    def _trigger_queued(self, remaining_s: float) -> None:
        self.show_message(f"Trigger queued: fires when the baseline is in ({remaining_s:.1f} s to go).")

    def _trigger_time(self, t: float, measured: bool) -> None:
        self.live.set_trigger(float(t), measured)  # the estimate at the command, then the measured instant
        if measured:
            self.show_message(f"Trigger measured from the valve position: t = {t:.4f} s on the run's axis; "
                              "the plot's t = 0 is now this instant")

    def _triggered(self, t) -> None:
        self.show_message(f"Triggered at t = {t:.3f} s (estimate at the command)")

    def _phase_info(self, phase: str, data) -> None:
        reason = data.get("reason") if isinstance(data, dict) else ""
        if phase == "ready" and data.get("devices"):
            self._devices_ready(data["devices"])
        elif phase == "aborted" and reason and reason.startswith("armed timeout"):
            self.show_message(f"Disarmed — {reason}", "warning")
        elif phase in ("stopped", "aborted", "failed") and reason:
            self.show_message(f"Run {phase}: {reason}", "warning" if phase == "stopped" else "error")

    def _refresh_plot(self) -> None:
        if self.live.refresh():
            rate = self.run_panel.rate_combo.currentData()
            self.run_page.show_stats(float(rate))
            if self.live.buffer.n:
                self.devices.update_readings({"head": _Reading(float(self.live.buffer.column("head_m")[-1]), "m")})

    def _fault(self, data) -> None:
        """A ``fault`` event: {"device", "message", "kind", "role"...} (velab.recording.Fault)."""
        dev = str(data.get("device") or "device")
        msg = str(data.get("message", ""))
        self.devices.set_fault(dev, msg)
        what = "Storage failure" if data.get("kind") == "storage" else "Device fault"
        self.show_message(f"{what} — {dev}: {msg}", "error")

    def _fit_event(self, data) -> None:
        """An online fit (intermediate or final) from the engine: the Run page says it, the Fit page shows it."""
        result, final = data["result"], bool(data.get("final", True))
        win = float(data.get("window_s", result.window_s))
        b = self.live.buffer
        t, h = b.column("time_s"), b.column("head_m")
        trig = self.live.trigger_time_s or 0.0
        pre = h[(t < trig) & np.isfinite(h)]
        steady = float(pre.mean()) if pre.size else (self.rig.steady_head_m if self.rig is not None else 0.0)
        sel = (t >= trig) & (t < trig + win)
        rig = self.rig or getattr(self.controller.recorder, "rig", None)
        label = "final fit" if final else f"online fit on the first {win:g} s"
        if rig is not None:
            self.fit_panel.set_fit(t[sel] - trig, h[sel] - steady, rig, result,
                                   title=f"{self.last_run_path.name if self.last_run_path else 'run'} — {label}")
        if not final:
            self.show_message(f"Online fit on {win:g} s: best so far {result.best.name}")

    def _done(self, summary) -> None:
        self.last_summary = summary
        trig = summary.trigger_time_s
        if isinstance(trig, (int, float)):
            self.live.set_trigger(float(trig), True)  # the instant measured from the valve position
        self.live.show_whole()
        text = f"Run {summary.status}" + (f" ({summary.reason})" if summary.reason else "")
        text += f": {summary.path}" if summary.path else ""
        peak = summary.peak_head_m
        text += f"; peak head {peak:.2f} m" if isinstance(peak, float) and np.isfinite(peak) else ""
        text += f"; best model {summary.best_model}" if summary.best_model else ""
        self.show_message(text, "info" if summary.status in ("completed", "stopped") else "warning")
        if summary.path:
            self.archive.set_folder(Path(summary.path).parent)
        fit = summary.fit
        if fit is not None and summary.path:
            path = summary.path
            tasks.submit(fit_window_of, path, fit.window_s,
                         owner=self, on_done=lambda th, f=fit, p=path: self._final_fit(p, f, *th),
                         on_error=lambda e: self.report_exception(e, "reading the run for the fit panel"))
        elif summary.fit_error:
            self.show_message(summary.fit_error, "warning")

    def _final_fit(self, path, fit, t, h, rig) -> None:
        self.fit_panel.set_fit(t, h, rig, fit, title=f"{Path(path).name} — final fit (stored as /entry/fits/online)")
        self.show_message(f"Fit: best model {fit.best.name} (a = {fit.best.wave_speed_m_s:.1f} m/s, "
                          f"weight {fit.best.weight:.2f})")


class _Reading:
    __slots__ = ("value", "units", "quality", "timestamp_s")

    def __init__(self, value, units, quality="ok"):
        self.value, self.units, self.timestamp_s = value, units, time.time()
        self.quality = quality if np.isfinite(value) else "nan"
