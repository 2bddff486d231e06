"""The operator's main window: Run page (devices, run controls, live plot), Fit page, Archive page,
and a message log. The window only reads state and sends commands (see controller.py)."""

from __future__ import annotations

import sys
import traceback
from pathlib import Path

import numpy as np
from PySide6.QtCore import QSettings, Qt, QTimer, Signal
from PySide6.QtGui import QAction, QGuiApplication, QKeySequence
from PySide6.QtWidgets import (QDockWidget, QGroupBox, QLabel, QMainWindow, QScrollArea, QSplitter, QTabWidget,
                               QVBoxLayout, QWidget)

from velab.gui import tasks
from velab.gui.archive import ArchiveBrowser
from velab.gui.controller import RecorderController
from velab.recording.safety import predict_surge
from velab.recording.settings import RecordSettings
from velab.gui.devices import DevicePanel
from velab.gui.fit_panel import FitPanel
from velab.gui.live_plot import LivePlot
from velab.gui.messages import Banner, MessageLog, describe_error
from velab.gui.run_panel import RunPanel

ORG, APP = "velab", "velab-gui"


def make_settings(path=None) -> QSettings:
    """The GUI's persistent settings: an INI file at ``path``, else the user's (org velab, app velab-gui)."""
    if path:
        return QSettings(str(path), QSettings.IniFormat)
    return QSettings(QSettings.IniFormat, QSettings.UserScope, ORG, APP)


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

        # ------------------------------------------------------------ run page
        run_page = QWidget()
        rl = QVBoxLayout(run_page)
        rl.setContentsMargins(4, 4, 4, 4)
        self.banner = Banner()
        rl.addWidget(self.banner)
        self.run_split = QSplitter(Qt.Horizontal)
        rl.addWidget(self.run_split, 1)
        left = QWidget()
        ll = QVBoxLayout(left)
        ll.setContentsMargins(0, 0, 0, 0)
        dev_box = QGroupBox("Devices")
        dl = QVBoxLayout(dev_box)
        self.devices = DevicePanel()
        dl.addWidget(self.devices)
        ll.addWidget(dev_box)
        self.run_panel = RunPanel(self.qs, rig=rig)
        ll.addWidget(self.run_panel)
        scroll = QScrollArea()
        scroll.setWidgetResizable(True)
        scroll.setWidget(left)
        scroll.setMinimumWidth(300)
        scroll.setHorizontalScrollBarPolicy(Qt.ScrollBarAlwaysOff)
        self.run_split.addWidget(scroll)
        right = QWidget()
        rr = QVBoxLayout(right)
        rr.setContentsMargins(0, 0, 0, 0)
        self.live = LivePlot()
        rr.addWidget(self.live, 1)
        self.run_stats = QLabel("No run yet.")
        rr.addWidget(self.run_stats)
        self.run_split.addWidget(right)
        self.run_split.setStretchFactor(0, 0)
        self.run_split.setStretchFactor(1, 1)
        self.run_split.setSizes([360, 900])
        self.tabs.addTab(run_page, "Run")

        # ------------------------------------------------------------ fit page
        self.fit_panel = FitPanel(title="No fit yet: the fit of each run appears here.")
        self.tabs.addTab(self.fit_panel, "Fit")

        # ------------------------------------------------------------ archive page
        self.archive = ArchiveBrowser(self.qs)
        self.archive.message.connect(self.show_message)
        self.tabs.addTab(self.archive, "Archive")

        # ------------------------------------------------------------ messages
        self.log = MessageLog()
        dock = QDockWidget("Messages", self)
        dock.setObjectName("messages")
        dock.setWidget(self.log)
        dock.setFeatures(QDockWidget.DockWidgetMovable | QDockWidget.DockWidgetFloatable
                         | QDockWidget.DockWidgetClosable)
        self.addDockWidget(Qt.BottomDockWidgetArea, dock)
        self.resizeDocks([dock], [110], Qt.Vertical)
        self.messages_dock = dock
        self.phase_label = QLabel("idle")
        self.phase_label.setMinimumWidth(110)
        self.phase_label.setAlignment(Qt.AlignCenter)
        self.statusBar().addPermanentWidget(self.phase_label)

        self._menus()

        # ------------------------------------------------------------ controller
        self.controller = None
        if recorder_factory is not None:
            self.controller = c = RecorderController(recorder_factory, self)
            c.phase_changed.connect(self._phase)
            c.phase_info.connect(self._phase_info)
            c.samples.connect(self._samples)
            c.devices.connect(self.devices.update_readings)
            c.device_status.connect(self._device_status)
            c.fit.connect(self._fit_event)
            c.message.connect(self.show_message)
            c.fault.connect(self._fault)
            c.done.connect(self._done)
            c.armed.connect(self._armed)
            c.triggered.connect(self._triggered)
            c.trigger_time.connect(self._trigger_time)
            c.valve.connect(self._valve)
            c.valve_reset.connect(self._valve_reset)
            self.devices.reconnect_requested.connect(self.connect_devices)
            self.run_panel.arm_clicked.connect(self.arm)
            self.run_panel.trigger_clicked.connect(c.trigger)
            self.run_panel.stop_clicked.connect(c.stop)
            self.run_panel.abort_clicked.connect(lambda: c.abort("operator abort"))
            self.run_panel.reset_valve_clicked.connect(self.reset_valve)
            self.run_panel.changed.connect(self.update_prediction)
        else:
            self.run_panel.setEnabled(False)
            self.devices.setEnabled(False)
            self.devices.set_state("No bench: start with --simulate or --config BENCH.toml to record.")
        self.plot_timer = QTimer(self)
        self.plot_timer.setInterval(100)
        self.plot_timer.timeout.connect(self._refresh_plot)
        self.plot_timer.start()
        self._restore()
        self.update_prediction()

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
        self.reset_valve_action.triggered.connect(lambda: self.reset_valve())
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
            w = min(1340, avail.width() - 20) if avail else 1280
            h = min(740, avail.height() - 40) if avail else 720
            self.resize(max(w, 800), max(h, 560))
        state = self.qs.value("window/state")
        if state is not None:
            self.restoreState(state)
        for key, split in (("window/run_split", self.run_split), ("window/archive_split", self.archive.splitter),
                           ("window/fit_split", self.fit_panel.splitter)):
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
        self.qs.setValue("window/fit_split", self.fit_panel.splitter.saveState())
        self.qs.setValue("window/tab", self.tabs.currentIndex())
        self.run_panel.save()
        self.qs.sync()

    def closeEvent(self, event) -> None:
        self.save_settings()
        if self.controller is not None:
            self.controller.close()
        tasks.wait_idle(5000)
        super().closeEvent(event)

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

    # ------------------------------------------------------------------ run
    def connect_devices(self) -> None:
        self.show_message("Connecting the devices…")
        self.controller.connect_devices(self._record_settings())

    def arm(self) -> None:
        s = self._record_settings()
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
        self.controller.arm(s)

    def _record_settings(self) -> dict:
        return self.run_panel.settings()

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
        pred = self._predict()
        if isinstance(pred, BaseException):
            self.run_panel.show_settings_error(describe_error(pred)[1])
        else:
            self.run_panel.show_prediction(pred)

    def _device_status(self, statuses) -> None:
        self.devices.update_status(statuses)
        self.update_prediction()
        bad = [s for s in (statuses or []) if getattr(s, "ok", getattr(s, "connected", True)) is False]
        if bad:
            self.show_message("Not connected: " + ", ".join(f"{getattr(s, 'name', s)} ({getattr(s, 'message', '')})"
                                                           for s in bad), "error")
        else:
            self.show_message(f"Devices connected ({len(statuses or [])}).")

    def _armed(self, path) -> None:
        self.last_run_path = Path(path) if path else None
        self.show_message(f"Armed: recording to {path}. Press Trigger to close the valve.")

    def reset_valve(self) -> None:
        if self.controller is None:
            return
        self.controller.reset_valve()

    def _valve(self, info) -> None:
        closed = isinstance(info, dict) and not info.get("open", True)
        self.run_panel.set_valve_closed(closed)
        self.reset_valve_action.setEnabled(self.run_panel.reset_valve_button.isEnabled())

    def _valve_reset(self, st) -> None:
        state = getattr(getattr(st, "state", None), "name", "")
        pos = getattr(getattr(st, "position", None), "value", None)
        self.show_message("Valve reopened" + (f": actuator {state}" if state else "")
                          + (f", {pos:.1f} % open" if isinstance(pos, (int, float)) else "") + ". Ready to arm.")

    def _trigger_time(self, t: float, measured: bool) -> None:
        self.live.set_trigger(float(t))  # the estimate at the command, then the instant measured from the valve
        if measured:
            self.show_message(f"Trigger measured from the valve position: t = {t:.4f} s")

    def _triggered(self, t) -> None:
        self.show_message(f"Triggered at t = {t:.3f} s" if isinstance(t, (int, float)) else "Triggered")

    def _phase(self, phase: str) -> None:
        self.phase_label.setText(phase)
        colors = {"armed": "#fff0c2", "triggerable": "#fff0c2", "recording": "#ffd9a8", "fitting": "#dbe9ff",
                  "completed": "#d8f0d2", "completed-with-faults": "#fbe7c6", "aborted": "#f9d0cd",
                  "failed": "#f9d0cd", "stopped": "#eeeeee"}
        self.phase_label.setStyleSheet(f"background:{colors.get(phase, 'transparent')}; padding:2px;")
        self.run_panel.set_phase(phase)
        self.reset_valve_action.setEnabled(self.run_panel.reset_valve_button.isEnabled())
        if phase == "recording" and self.live.trigger_time_s is None:
            self.live.set_trigger(0.0)

    def _samples(self, t, h, v, lost) -> None:
        self.live.append(t, h, v, lost)

    def _phase_info(self, phase: str, data) -> None:
        t = data.get("trigger_time_s") if isinstance(data, dict) else None
        if phase == "recording" and isinstance(t, (int, float)):
            self.live.set_trigger(float(t))
        if phase in ("stopped", "aborted", "failed") and isinstance(data, dict) and data.get("reason"):
            self.show_message(f"Run {phase}: {data['reason']}", "warning" if phase == "stopped" else "error")

    def _refresh_plot(self) -> None:
        if self.live.refresh():
            b = self.live.buffer
            if b.n:
                head = b.column("head_m")
                self.devices.update_readings({"head (ADC)": _Reading(float(head[-1]), "m")})
                rate = self.run_panel.settings()["sample_rate_hz"]
                self.run_stats.setText(
                    f"{b.n} samples ({rate:g} Hz), t = {b.column('time_s')[-1]:.2f} s, "
                    f"head {head[-1]:.2f} m (max {np.nanmax(head):.2f} m), lost {self.live.lost_samples}")

    def _fault(self, data) -> None:
        """A ``fault`` event: {"device", "message", "kind", "role"...} (velab.recording.Fault)."""
        if isinstance(data, dict):
            dev = str(data.get("device") or "device")
            msg = str(data.get("message", ""))
        else:  # an engine without structured faults: the text only
            dev, msg = "device", str(data)
        self.devices.set_fault(dev, msg)
        what = "Storage failure" if isinstance(data, dict) and data.get("kind") == "storage" else "Device fault"
        self.show_message(f"{what} — {dev}: {msg}", "error")

    def _fit_event(self, data) -> None:
        result = data.get("result") if isinstance(data, dict) else data
        if result is None:
            return
        final = bool(data.get("final", True)) if isinstance(data, dict) else True
        b = self.live.buffer
        t = b.column("time_s")
        h = b.column("head_m")
        trig = self.live.trigger_time_s or 0.0
        pre = h[(t < trig) & np.isfinite(h)]
        steady = float(pre.mean()) if pre.size else (self.rig.steady_head_m if self.rig is not None else 0.0)
        win = float(data.get("window_s", result.window_s)) if isinstance(data, dict) else result.window_s
        sel = (t >= trig) & (t < trig + win)
        label = "final fit" if final else f"online fit on the first {win:g} s"
        rig = self.rig or getattr(self.controller.recorder, "rig", None)
        if rig is None:
            return
        self.fit_panel.set_fit(t[sel] - trig, h[sel] - steady, rig, result,
                               title=f"{self.last_run_path.name if self.last_run_path else 'run'} — {label}")
        if not final:
            self.show_message(f"Online fit on {win:g} s: best so far {result.best.name}")

    def _done(self, summary) -> None:
        self.last_summary = summary
        self.live.show_whole()
        status = getattr(summary, "status", "?")
        reason = getattr(summary, "reason", "")
        path = getattr(summary, "path", None)
        best = getattr(summary, "best_model", None)
        peak = getattr(summary, "peak_head_m", float("nan"))
        text = f"Run {status}" + (f" ({reason})" if reason else "") + (f": {path}" if path else "")
        text += f"; peak head {peak:.2f} m" if isinstance(peak, float) and np.isfinite(peak) else ""
        text += f"; best model {best}" if best else ""
        level = "info" if status in ("completed", "done", "stopped") else "warning"
        self.show_message(text, level)
        if path:
            self.archive.set_folder(Path(path).parent)
        trig = getattr(summary, "trigger_time_s", None)
        if isinstance(trig, (int, float)):
            self.live.set_trigger(float(trig))  # the instant measured from the valve position
        fit = getattr(summary, "fit", None)
        if fit is not None and path:
            from velab.gui.archive_io import fit_window_of

            tasks.submit(fit_window_of, path, fit.window_s,
                         on_done=lambda th, f=fit, p=path: self._final_fit(p, f, *th),
                         on_error=lambda e: self.report_exception(e, "reading the run for the fit panel"))
        elif getattr(summary, "fit_error", ""):
            self.show_message(summary.fit_error, "warning")

    def _final_fit(self, path, fit, t, h, rig) -> None:
        self.fit_panel.set_fit(t, h, rig, fit, title=f"{Path(path).name} — final fit (stored as /entry/fits/online)")
        self.show_message(f"Fit: best model {fit.best.name} (a = {fit.best.wave_speed_m_s:.1f} m/s, "
                          f"weight {fit.best.weight:.2f})")


class _Reading:
    __slots__ = ("value", "units", "quality", "timestamp_s")

    def __init__(self, value, units, quality="ok"):
        import time as _t

        self.value, self.units, self.timestamp_s = value, units, _t.time()
        self.quality = quality if np.isfinite(value) else "nan"
