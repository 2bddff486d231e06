"""The bridge between the recorder engine (velab.recording, Qt-free) and the window.

ScopeFoundry's split: the engine does all device I/O and file writing on its own
threads and publishes :class:`RecorderEvent`s on a queue; the GUI drains that queue
on a QTimer (every ``tick_ms``, with a bounded amount of work per tick), re-emits
the events as Qt signals, posts commands (which return ``concurrent.futures.Future``)
and polls their completion on the same timer. Nothing here blocks on a device.

The controller makes a Recorder (through ``factory(**settings)``) on the first
Connect or Arm and keeps it: further runs are armed on the same connection (the new
settings go with the arm command; ``factory.make_settings(**settings)``, if the factory
has it, turns the form's values into RecordSettings on the worker thread). After a run
the valve is closed: ``reset_valve()`` reopens it, and Arm after a run does that first
(not from an actuator FAULT: that needs the operator's Reset valve). *Reconnect* makes a
new Recorder (a new connection).
"""

from __future__ import annotations

import queue
import time
import traceback
from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import numpy as np
from PySide6.QtCore import QObject, QTimer, Signal

from velab.gui.messages import describe_error

from velab.recording.phases import ACTIVE_PHASES


class RecorderController(QObject):
    phase_changed = Signal(str)
    phase_info = Signal(str, object)  # phase, the event's data (path, trigger_time_s, status, reason...)
    samples = Signal(object, object, object, int)  # time_s, head_m, valve_position, lost
    devices = Signal(object)  # name -> Reading
    device_status = Signal(object)  # list of DeviceStatus
    fit = Signal(object)  # dict(result=SweepResult, final=bool, window_s=float)
    message = Signal(str, str)  # text, level
    fault = Signal(object)  # event data
    done = Signal(object)  # RunSummary
    armed = Signal(object)  # the run file path
    triggered = Signal(float)
    trigger_time = Signal(float, bool)  # the trigger instant on the run's axis; measured (True) or estimated
    valve = Signal(object)  # dict: device, state, position_pct, open, faults
    valve_reset = Signal(object)  # the actuator's status after reset_valve
    command_failed = Signal(str, object)  # command name, exception

    def __init__(self, factory: Callable, parent=None, *, tick_ms: int = 50, budget_s: float = 0.012):
        super().__init__(parent)
        self.factory = factory
        self.recorder = None
        self.phase = "disconnected"
        self.budget_s = budget_s
        self._pending: list[tuple[str, object, Callable | None]] = []
        self._settings: dict | None = None
        self._connected = False  # the current recorder's devices answered (connect succeeded)
        self.valve_info: dict | None = None  # the last "valve" event
        self.events_seen = 0
        # making and closing a Recorder starts/stops devices (or the simulator): never on the GUI thread
        self._exec = ThreadPoolExecutor(max_workers=1, thread_name_prefix="velab-gui-recorder")
        self._making = False
        self.timer = QTimer(self)
        self.timer.setInterval(tick_ms)
        self.timer.timeout.connect(self.drain)
        self.timer.start()

    # ------------------------------------------------------------------ commands
    def busy(self) -> bool:
        return (self._making or self.phase in ACTIVE_PHASES
                or any(name in ("connect", "arm", "reset", "settings") for name, _, _ in self._pending))

    def valve_closed(self) -> bool:
        """The last actuator status the engine published says the valve is not open (and idle)."""
        return self.valve_info is not None and not self.valve_info.get("open", True)

    def connect_devices(self, settings: dict) -> None:
        """Make a fresh Recorder for ``settings`` (a new connection) and connect its devices."""
        if self.busy():
            self.message.emit(f"Cannot reconnect while the recorder is {self.phase}.", "warning")
            return
        self._replace(settings, then=lambda: self._post("connect", lambda: self.recorder.connect(),
                                                        self._connected_ok))

    def _connected_ok(self, statuses) -> None:
        self._connected = True
        self.device_status.emit(statuses)

    def arm(self, settings: dict) -> None:
        """Arm a run with ``settings`` on the connected Recorder (made and connected first if there is none).

        After a run the valve is reopened first (``reset_valve``) unless the actuator is in FAULT.
        """
        if self.busy():
            self.message.emit(f"Cannot arm: the recorder is {self.phase}.", "warning")
            return
        rec = self.recorder
        if rec is None or not self._connected:
            def then():
                self._post("connect", lambda: self.recorder.connect(),
                           lambda st: (self._connected_ok(st),
                                       self._post("arm", lambda: self.recorder.arm(), self.armed.emit)))
            self._replace(settings, then=then)
            return
        reset_first = self.valve_closed() and (self.valve_info or {}).get("state") != "FAULT"

        def arm_with(rs):
            if reset_first:
                self.message.emit("The valve is closed after the last run: reopening it before arming…", "info")
                self._post("reset", lambda: rec.reset_valve(),
                           lambda st: (self.valve_reset.emit(st), self._post("arm", lambda: arm_call(rs), self.armed.emit)))
            else:
                self._post("arm", lambda: arm_call(rs), self.armed.emit)

        def arm_call(rs):
            return rec.arm() if rs is None else rec.arm(settings=rs)

        if settings == self._settings:
            arm_with(None)
            return
        self._settings = dict(settings)
        make = getattr(self.factory, "make_settings", None)
        if make is None:
            arm_with(dict(settings))
        else:  # RecordSettings (and the run folder) on the worker thread
            self._pending.append(("settings", self._exec.submit(lambda: make(**settings)), arm_with))

    def reset_valve(self) -> None:
        """Reopen the valve (actuator reset; the flow gets 1 s to settle) on the current connection."""
        if self.recorder is None:
            self.message.emit("Connect the bench first.", "warning")
            return
        if self.busy():
            self.message.emit(f"Cannot reset the valve: the recorder is {self.phase}.", "warning")
            return
        rec = self.recorder
        self.message.emit("Resetting the valve actuator (reopening the valve)…", "info")
        self._post("reset", lambda: rec.reset_valve(), self.valve_reset.emit)

    def trigger(self) -> None:
        if self.recorder is None:
            return
        self._post("trigger", lambda: self.recorder.trigger(), self.triggered.emit)

    def stop(self) -> None:
        if self.recorder is None:
            return
        self._post("stop", lambda: self.recorder.stop(), None)

    def abort(self, reason: str = "operator abort") -> None:
        if self.recorder is None:
            return
        self._post("abort", lambda: self.recorder.abort(reason), None)

    def predict_surge(self, beta_per_s=None, gamma=None):
        """The recorder's pure surge prediction, or None before a recorder exists."""
        if self.recorder is None:
            return None
        return self.recorder.predict_surge(beta_per_s=beta_per_s, gamma=gamma)

    def close(self) -> None:
        """Closing the window: abort an active run, release the devices (in the background, bounded)."""
        self.timer.stop()
        rec, self.recorder = self.recorder, None

        def shut():
            if rec is None:
                return
            try:
                if self.phase in ACTIVE_PHASES:
                    rec.abort("window closed").result(timeout=10)
            except Exception:
                pass
            try:
                rec.close()
            except Exception:  # closing must not raise
                traceback.print_exc()
        fut = self._exec.submit(shut)
        self._exec.shutdown(wait=False)
        try:
            fut.result(timeout=20)
        except Exception:
            pass

    # ------------------------------------------------------------------ internals
    def _replace(self, settings: dict, then: Callable) -> None:
        """Close the current Recorder and make a new one, on the worker thread; then ``then()``."""
        old, self.recorder = self.recorder, None
        self._settings = dict(settings)
        self._connected = False
        self.valve_info = None
        self._making = True
        self._set_phase("connecting")

        def make():
            if old is not None:
                try:
                    old.close()
                except Exception:
                    traceback.print_exc()
            return self.factory(**settings)

        def made(rec):
            self._making = False
            self.recorder = rec
            then()
        self._pending.append(("setup", self._exec.submit(make), made))

    def _post(self, name: str, call: Callable, on_ok: Callable | None) -> None:
        try:
            fut = call()
        except Exception as exc:  # a command refused synchronously (interlock, bad state)
            self._failed(name, exc)
            return
        self._pending.append((name, fut, on_ok))

    def _failed(self, name: str, exc: BaseException) -> None:
        if name == "settings":
            self._settings = None  # not applied: the next Arm converts the form again
        if name == "setup":
            self._making = False
            self._set_phase("disconnected" if self.recorder is None else getattr(self.recorder, "phase", "disconnected"))
        level, text = describe_error(exc)
        self.command_failed.emit(name, exc)
        self.message.emit(text, level)

    def _set_phase(self, phase: str) -> None:
        if phase != self.phase:
            self.phase = phase
            self.phase_changed.emit(phase)

    def drain(self) -> None:
        """One timer tick: finished commands, then queued events, within the time budget."""
        if self._pending:
            pending, self._pending = self._pending, []
            for name, fut, on_ok in pending:
                if not fut.done():
                    self._pending.append((name, fut, on_ok))
                    continue
                exc = fut.exception()
                if exc is not None:
                    self._failed(name, exc)
                elif on_ok is not None:
                    try:
                        on_ok(fut.result())  # may post the next command
                    except Exception as e:  # a GUI callback must not kill the timer
                        self.message.emit(f"Internal error after {name}: {e}", "error")
                        traceback.print_exc()
        rec = self.recorder
        if rec is None:
            return
        q = rec.events
        deadline = time.perf_counter() + self.budget_s
        blocks_t, blocks_h, blocks_v, lost = [], [], [], 0
        while time.perf_counter() < deadline:
            try:
                ev = q.get_nowait()
            except queue.Empty:
                break
            self.events_seen += 1
            kind = ev.kind
            if kind == "samples":
                d = ev.data
                blocks_t.append(np.asarray(d["time_s"]))
                blocks_h.append(np.asarray(d["head_m"]))
                v = d.get("valve_position")
                blocks_v.append(np.asarray(v) if v is not None else np.full(np.shape(d["time_s"]), np.nan))
                lost += int(d.get("lost", 0) or 0)
                continue
            if blocks_t:  # keep the order of samples and other events
                self._emit_samples(blocks_t, blocks_h, blocks_v, lost)
                blocks_t, blocks_h, blocks_v, lost = [], [], [], 0
            self._dispatch(ev)
        if blocks_t:
            self._emit_samples(blocks_t, blocks_h, blocks_v, lost)
        ph = getattr(rec, "phase", None)
        if isinstance(ph, str) and not self._making and q.empty():
            self._set_phase(ph)  # the engine's phase, once its events are all in

    def _emit_samples(self, ts, hs, vs, lost) -> None:
        self.samples.emit(np.concatenate(ts), np.concatenate(hs), np.concatenate(vs), lost)

    def _dispatch(self, ev) -> None:
        kind, data = ev.kind, ev.data
        if kind == "phase":
            phase = data if isinstance(data, str) else (data.get("phase") if isinstance(data, dict) else str(data))
            self._set_phase(phase)
            self.phase_info.emit(phase, data if isinstance(data, dict) else {})
        elif kind == "device":
            self.devices.emit(data)
        elif kind == "valve":
            self.valve_info = dict(data) if isinstance(data, dict) else None
            self.valve.emit(data)
        elif kind == "trigger":
            if isinstance(data, dict) and isinstance(data.get("trigger_time_s"), (int, float)):
                self.trigger_time.emit(float(data["trigger_time_s"]), bool(data.get("measured", False)))
        elif kind == "fit":
            self.fit.emit(data)
        elif kind == "message":
            if isinstance(data, dict):
                self.message.emit(str(data.get("text", data.get("message", data))), str(data.get("level", "info")))
            else:
                self.message.emit(str(data), "info")
        elif kind == "fault":
            self.fault.emit(data)
        elif kind == "done":
            self.done.emit(data)
