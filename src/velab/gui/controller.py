"""The bridge between the recorder engine (velab.recording, Qt-free) and the window.

ScopeFoundry's split: the engine does all device I/O and file writing on its own threads
and publishes :class:`RecorderEvent`s on a queue; on a QTimer (every ``tick_ms``) the
controller collects its finished commands (``concurrent.futures.Future``), drains the
event queue within a time budget, re-emits the events as Qt signals, and reads the engine's
phase and allowed commands: ``state`` (a :class:`~velab.gui.state.ControlState`) is that,
plus the window's own commands in flight, and ``state_changed`` says when it changes.
Nothing here blocks on a device.

The controller makes a Recorder (``factory(**settings)``, on its worker thread) on the
first Connect, Arm or Reset valve and keeps it: further runs are armed on the same
connection with the form's settings (``factory.make_settings``, also on the worker: it
creates the run folder). Connect makes a new Recorder (a new connection). Arm after a run
that closed the valve reopens it first (``reset_valve``), not from an actuator FAULT.
A Trigger pressed while the baseline fills is queued by the engine and settles when it is
carried out, or with "trigger cancelled" when the run ends first (``trigger_cancelled``).
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
from velab.gui.spot import spot_readings
from velab.gui.state import ControlState
from velab.recording import phases as P

LOOK_EVERY_S = 2.0  # the device table's spot reading between runs (velab.gui.spot)


class RecorderController(QObject):
    state_changed = Signal(object)  # ControlState
    phase_changed = Signal(str)
    phase_info = Signal(str, object)  # a ``phase`` event: phase, its data (path, reason, ...)
    samples = Signal(object, object, object, int)  # time_s, head_m, valve_position, lost
    devices = Signal(object)  # name -> Reading
    device_status = Signal(object)  # list of DeviceStatus
    fit = Signal(object)  # dict(result=SweepResult, final=bool, window_s=float)
    message = Signal(str, str)  # text, level
    fault = Signal(object)  # event data
    done = Signal(object)  # RunSummary
    armed = Signal(object)  # the run file path
    triggered = Signal(float)  # the trigger was carried out (estimated instant)
    trigger_queued = Signal(float)  # baseline still to record, s
    trigger_cancelled = Signal(str)
    trigger_time = Signal(float, bool)  # the trigger instant on the run's axis; measured (True) or estimated
    valve = Signal(object)  # dict: device, state, position_pct, open, faults
    valve_reset = Signal(object)  # the actuator's status after reset_valve
    command_failed = Signal(str, object)  # command name, exception

    def __init__(self, factory: Callable, parent=None, *, tick_ms: int = 50, budget_s: float = 0.012):
        super().__init__(parent)
        self.factory = factory
        self.recorder = None
        self.budget_s = budget_s
        self._pending: list[tuple[str, object, Callable | None]] = []
        self._local = {"phase": P.DISCONNECTED, "data": {}}  # before a Recorder exists / after one failed
        self._progress: dict = {}
        self.valve_info: dict | None = None  # the last "valve" event
        self.run_info: dict = {}  # the armed run's duration_s, fit, fit_window_s, final_fit (ControlState.run)
        self.refusal = ""  # the interlock refuses the form's settings (set_refusal): Arm is not offered
        self._look = None  # the spot reading in flight (a Future on the engine's control thread)
        self._last_look = 0.0
        self.state = ControlState(allowed=P.allowed_commands(P.DISCONNECTED))
        self.events_seen = 0
        # making and closing a Recorder starts/stops devices (or the simulator): never on the GUI thread
        self._exec = ThreadPoolExecutor(max_workers=1, thread_name_prefix="velab-gui-recorder")
        self.timer = QTimer(self)
        self.timer.setInterval(tick_ms)
        self.timer.timeout.connect(self.drain)
        self.timer.start()

    @property
    def phase(self) -> str:
        return self.state.phase

    def can(self, action: str) -> bool:
        return self.state.controls().get(action, False)

    def _refuse(self, action: str) -> bool:
        """True (and says why) when ``action`` cannot succeed now; the buttons make this rare."""
        if self.can(action):
            return False
        self.message.emit(f"{action.replace('_', ' ').capitalize()} is not possible now ({self.phase}).", "warning")
        return True

    # ------------------------------------------------------------------ commands
    def connect_devices(self, settings: dict) -> None:
        """Make a fresh Recorder for ``settings`` (a new connection) and connect its devices."""
        if self._refuse("connect"):
            return
        self._replace(settings, then=lambda: self._post("connect", lambda: self.recorder.connect(),
                                                        self.device_status.emit))

    def arm(self, settings: dict) -> None:
        """Arm a run with ``settings``: on the current Recorder (the engine connects first if needed),
        or a new one; after a run that closed the valve, the valve is reopened first."""
        if self._refuse("arm"):
            return
        self.run_info = {"duration_s": settings.get("duration_s"), "fit": bool(settings.get("fit", True)),
                         "fit_window_s": settings.get("fit_window_s"), "final_fit": False}
        if self.recorder is None:
            self._replace(settings, then=lambda: self._arm_on(self.recorder, settings, reopen=False))
        else:
            self._arm_on(self.recorder, settings, reopen=self.state.reopen_before_arm)

    def _arm_on(self, rec, settings: dict, reopen: bool) -> None:
        def arm_with(rs):
            if reopen:
                self.message.emit("The valve is closed after the last run: reopening it before arming…", "info")
                self._post("reset", rec.reset_valve,
                           lambda st: (self.valve_reset.emit(st), self._post("arm", lambda: rec.arm(settings=rs),
                                                                             self.armed.emit)))
            else:
                self._post("arm", lambda: rec.arm(settings=rs), self.armed.emit)

        make = getattr(self.factory, "make_settings", None)
        if make is None:
            arm_with(dict(settings))
        else:  # RecordSettings (and the run folder) on the worker thread
            self._pending.append(("settings", self._exec.submit(lambda: make(**settings)), arm_with))
            self._update_state()

    def reset_valve(self, settings: dict | None = None) -> None:
        """Reopen the valve (actuator reset; the flow gets 1 s to settle), connecting first if needed."""
        if self._refuse("reset_valve"):
            return
        self.message.emit("Resetting the valve actuator (reopening the valve)…", "info")
        if self.recorder is None:
            self._replace(settings or {}, then=lambda: self._post("reset", self.recorder.reset_valve,
                                                                  self.valve_reset.emit))
        else:
            self._post("reset", self.recorder.reset_valve, self.valve_reset.emit)

    def trigger(self) -> None:
        if self._refuse("trigger"):
            return
        self._post("trigger", self.recorder.trigger, self.triggered.emit)

    def stop(self) -> None:
        if self._refuse("stop"):
            return
        self._post("stop", self.recorder.stop, None)

    def abort(self, reason: str = "operator abort") -> None:
        if self._refuse("abort"):
            return
        rec = self.recorder
        self._post("abort", lambda: rec.abort(reason), None)

    def set_refusal(self, why: str) -> None:
        """The interlock's verdict on the form's settings, from the window: non-empty = it would refuse them."""
        if why != self.refusal:
            self.refusal = why
            self._update_state()

    def predict_surge(self, beta_per_s=None, gamma=None):
        """The recorder's pure surge prediction, or None before a recorder exists."""
        if self.recorder is None:
            return None
        return self.recorder.predict_surge(beta_per_s=beta_per_s, gamma=gamma)

    def close(self) -> None:
        """Closing the window: abort an active run, release the devices (in the background, bounded)."""
        self.timer.stop()
        rec, self.recorder = self.recorder, None
        phase = self.phase
        making = [fut for name, fut, _ in self._pending if name == "setup"]  # a Recorder still being made

        def shut():
            recs = [rec] if rec is not None else []
            for fut in making:
                try:
                    recs.append(fut.result(timeout=30))
                except Exception:
                    pass
            for r in recs:
                try:
                    if r is rec and phase in P.RUN_PHASES:
                        r.abort("window closed").result(timeout=10)
                except Exception:
                    pass
                try:
                    r.close()
                except Exception:  # closing must not raise
                    traceback.print_exc()
        fut = self._exec.submit(shut)
        self._exec.shutdown(wait=False)
        try:
            fut.result(timeout=60)
        except Exception:
            pass

    # ------------------------------------------------------------------ internals
    def _replace(self, settings: dict, then: Callable) -> None:
        """Close the current Recorder and make a new one, on the worker thread; then ``then()``."""
        old, self.recorder = self.recorder, None
        self.valve_info = None
        self._progress = {}
        self._local = {"phase": P.DISCONNECTED, "data": {}}

        def make():
            if old is not None:
                try:
                    old.close()
                except Exception:
                    traceback.print_exc()
            return self.factory(**settings)

        def made(rec):
            self.recorder = rec
            then()
        self._pending.append(("setup", self._exec.submit(make), made))
        self._update_state()

    def _post(self, name: str, call: Callable, on_ok: Callable | None) -> None:
        try:
            fut = call()
        except Exception as exc:  # a command refused synchronously
            self._failed(name, exc)
            return
        self._pending.append((name, fut, on_ok))
        self._update_state()

    def _failed(self, name: str, exc: BaseException) -> None:
        level, text = describe_error(exc)
        if name == "setup":
            self._local = {"phase": P.DISCONNECTED, "data": {"reason": text}}
        if name == "trigger" and "trigger cancelled" in str(exc):
            self.trigger_cancelled.emit(str(exc))
            self.message.emit(f"Queued trigger cancelled: {str(exc).split(': ', 1)[-1]}", "warning")
            return
        self.command_failed.emit(name, exc)
        self.message.emit(text, level)

    def drain(self) -> None:
        """One timer tick: finished commands, then queued events (within the time budget), then the state."""
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
        if rec is not None:
            self._drain_events(rec.events)
            self._spot(rec)
        self._update_state()

    def _spot(self, rec) -> None:
        """Between runs (ready, or a run's end), every LOOK_EVERY_S: the steady head, flow and valve for the
        device table (velab.gui.spot), on the engine's control thread, never beside one of the window's
        commands."""
        look = self._look
        if look is not None:
            if not look.done():
                return
            self._look = None
            if look.exception() is None and look.result():
                self.devices.emit(look.result())
        now = time.monotonic()
        if (self._pending or now - self._last_look < LOOK_EVERY_S
                or not (self.state.phase == P.READY or self.state.phase in P.END_PHASES)):
            return
        self._last_look = now
        submit = getattr(rec, "submit", None)  # (an engine without a command thread: no spot readings)
        if callable(submit):
            self._look = submit(lambda: spot_readings(rec))

    def _drain_events(self, q) -> None:
        deadline = time.perf_counter() + self.budget_s
        blocks_t, blocks_h, blocks_v, lost = [], [], [], 0
        while time.perf_counter() < deadline:
            try:
                ev = q.get_nowait()
            except queue.Empty:
                break
            self.events_seen += 1
            if ev.kind == "samples":
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

    def _update_state(self) -> None:
        """The engine's phase and allowed commands now, plus the window's commands in flight."""
        rec = self.recorder
        in_flight = tuple(name for name, _, _ in self._pending)
        if rec is None:
            phase, data = self._local["phase"], self._local["data"]
            allowed = P.allowed_commands(phase)
        else:
            snap = rec.snapshot  # one read: phase, data and allowed commands belong together
            phase, data, allowed = snap.phase, dict(snap.data), snap.allowed
        st = ControlState(phase=phase, allowed=allowed, data=data, progress=self._progress, in_flight=in_flight,
                          valve=self.valve_info, run=self.run_info,
                          refused=self.refusal)
        if st != self.state:
            old, self.state = self.state, st
            if old.phase != phase:
                self.phase_changed.emit(phase)
            self.state_changed.emit(st)

    def _emit_samples(self, ts, hs, vs, lost) -> None:
        self.samples.emit(np.concatenate(ts), np.concatenate(hs), np.concatenate(vs), lost)

    def _dispatch(self, ev) -> None:
        handler = self._HANDLERS.get(ev.kind)
        if handler is not None:
            handler(self, ev.data)

    def _on_valve(self, data) -> None:
        self.valve_info = dict(data)
        self.valve.emit(data)

    def _on_trigger(self, data) -> None:
        if data.get("queued"):
            self.trigger_queued.emit(float(data.get("baseline_remaining_s", 0.0)))
        elif isinstance(data.get("trigger_time_s"), (int, float)):
            self.trigger_time.emit(float(data["trigger_time_s"]), bool(data.get("measured", False)))

    def _on_progress(self, data) -> None:
        self._progress = dict(data)

    def _on_fit(self, data) -> None:
        if data.get("final", True):  # the final fit is in: the indicator stops saying "fitting"
            self.run_info = {**self.run_info, "final_fit": True}
        self.fit.emit(data)

    # each engine event kind (velab.recording.types.RecorderEvent) -> what the window is told
    # ("samples" are batched by _drain_events)
    _HANDLERS = {
        "phase": lambda self, d: self.phase_info.emit(d.get("phase", ""), d),
        "progress": _on_progress,
        "device": lambda self, d: self.devices.emit(d),
        "valve": _on_valve,
        "trigger": _on_trigger,
        "fit": _on_fit,
        "message": lambda self, d: self.message.emit(str(d), "info"),
        "fault": lambda self, d: self.fault.emit(d),
        "done": lambda self, d: self.done.emit(d),
    }
