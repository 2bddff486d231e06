"""The engine (``Recorder``): the device session, the command queue and the phase; ``arm`` makes a
``Run`` (velab.recording.run), which owns that run's stages and outcome.

Threads (none of them Qt): the *control* thread runs every command (queued, each returns a
``concurrent.futures.Future``), the run's timers (baseline countdown, queued trigger, armed
timeout) and is the only one to publish the phase (``snapshot``); the pressure stage's
*acquisition* thread feeds the time line; the slow channels poll the valve and the flowmeter;
the *writer* is the only one touching the file; the online fit runs on its own; a *conclude*
thread waits for the final fit and hands the summary to the control thread. A run's stages report
through its ``Hooks`` (emit, log, fault, request_end). docs/recording.md.
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import queue
import threading
import time
from types import MappingProxyType
from typing import Any, Callable

from velab.benchrig import rig_for_bench
from velab.rig import Rig
from velab.drivers.bench import open_device
from velab.drivers.valve import ValveState
from velab.errors import VelabError
from velab.recording import phases as P
from velab.drivers.identity import identity
from velab.drivers.pressure_source import pressure_source
from velab.recording.devices import bench_armed_timeout, check_valve_open, profile_contents, reopen_valve, resolve_roles
from velab.recording.events import EventQueue
from velab.recording.run import DEFER, Run
from velab.recording.safety import predict_surge
from velab.recording.settings import RecordSettings
from velab.recording.transducers import transducer_channels
from velab.recording.slow import valve_event
from velab.recording.types import (
    DEVICE_ERRORS, DeviceFailure, DeviceStatus, EngineSnapshot, Fault, RecorderEvent, RunSummary, failed_how)

log = logging.getLogger(__name__)


class Recorder:
    """One engine for ``velab record`` and the GUI: the device session, the command queue and the phase;
    each armed run is a ``Run`` (velab.recording.run). See the module docstring and docs/recording.md."""

    def __init__(self, bench, rig: Rig, settings: RecordSettings, *, sim=None, owns_sim: bool = False):
        # MV's characteristic from the valve's device profile unless the rig file names one (velab.benchrig):
        # the run file's rig is then the one the bench made the flow with
        self.bench, self.settings = bench, settings
        self.rig = rig_for_bench(rig, bench.devices, bench.recorder.get("valve"))
        self.sim, self._owns_sim = sim, owns_sim
        self.clock = getattr(sim, "clock", None)
        # device seconds per host second: the simulated rig's clock (1 at a real bench and on a manual clock)
        self.clock_scale = float(getattr(self.clock, "scale", 1.0)) if self.clock is not None else 1.0
        self.bench_armed_timeout_s = bench_armed_timeout(bench)
        self.bench_where = bench.path or bench.name  # (the bench's file, in its config errors)
        # the bench's channel map names transducers of this rig, and every one of them (its channels: at arm)
        transducer_channels(self.rig, bench.transducer_channels, self.bench_where)
        self.events = EventQueue(maxsize=1000)  # bounded: memory stays flat without a consumer
        # replaced whole (a tuple) when one is added: engine threads read it without a lock
        self._listeners: tuple[Callable[[RecorderEvent], None], ...] = ()
        # phase, its data and the commands allowed now: one immutable snapshot, replaced whole (any
        # thread reads it with one attribute read); only the control thread publishes it
        self.snapshot = EngineSnapshot(P.DISCONNECTED, MappingProxyType({}), P.allowed_commands(P.DISCONNECTED))
        self.devices: dict[str, Any] = {}
        self.roles: dict[str, str] = {}
        self.identities: dict[str, dict] = {}
        self.last_stroke = None  # the last run's measured stroke (Run._manoeuvre: a fired valve's next prediction)
        self.profiles: dict[str, dict] = {}
        self._valve_state: ValveState | None = None
        self._valve_position: float | None = None
        self._cmds: queue.Queue = queue.Queue()
        self._closing = threading.Event()
        self._current_fut: cf.Future | None = None
        self.current_run: Run | None = None  # the current (or last) run; replaced by the next arm
        self._control = threading.Thread(target=self._control_loop, name="velab-recorder-control", daemon=True)
        self._control.start()

    @classmethod
    def simulated(cls, settings: RecordSettings, sim_config: str = "default", material: str | None = None,
                  clock="realtime", rig: Rig | str | None = None) -> "Recorder":
        """Start the simulated rig in-process (ephemeral endpoints) and record from it; the Recorder owns it.

        ``clock``: "realtime", "fast" (12 x real time), "scaled:K", or a clock object. ``rig``: a rig's name or
        path makes the simulated rig that rig (``velab record --simulate --rig NAME``); a Rig object is the rig
        the recorder believes in while the simulator runs its config's (a wrong rig file, as a lab may have).
        """
        # not at module level: a recorder on a real bench never loads the simulators (servers, ptys)
        from velab.simulators.bench import SimulatedBench, load_sim_config
        from velab.simulators.clock import make_clock

        path, doc = load_sim_config(sim_config)
        doc = dict(doc)
        if material:
            doc["material"] = material
        if isinstance(rig, str):
            doc["rig"], rig = rig, None
        if isinstance(clock, str):
            try:
                clock = make_clock(clock)
            except ValueError as exc:
                raise VelabError(str(exc)) from None
        sim = SimulatedBench(doc, ephemeral=True, clock=clock, path=str(path)).start()
        try:
            return cls(sim.bench(), rig or sim.rig.rig, settings, sim=sim, owns_sim=True)
        except BaseException:
            sim.stop()
            raise

    # ------------------------------------------------------------------ events
    def add_listener(self, fn: Callable[[RecorderEvent], None]) -> None:
        """fn(RecorderEvent), called from engine threads (keep it short, thread-safe)."""
        self._listeners = self._listeners + (fn,)

    @property
    def events_dropped(self) -> int:
        return self.events.dropped

    @property
    def phase(self) -> str:
        return self.snapshot.phase

    @property
    def phase_data(self):
        return self.snapshot.data

    def emit(self, kind: str, data: Any) -> None:
        ev = RecorderEvent(kind, time.time(), data)
        self.events.offer(ev)  # a phase, fault or fit is never lost: live data make room
        for fn in self._listeners:
            try:
                fn(ev)
            except Exception:  # noqa: BLE001 - a listener's bug never stops a recording
                log.exception("recorder event listener")

    def allowed_commands(self) -> tuple[str, ...]:
        """The commands that can succeed now (the GUI enables exactly these)."""
        return self.snapshot.allowed

    def _publish(self, phase: str, data) -> None:
        """On the control thread: the new snapshot, in one assignment."""
        run = self.current_run
        allowed = P.allowed_commands(phase, valve_open=self.valve_open,
                                     trigger_queued=run is not None and run.trigger_fut is not None)
        self.snapshot = EngineSnapshot(phase, MappingProxyType(dict(data)), allowed)

    def set_phase(self, phase: str, **data) -> None:
        self._publish(phase, data)
        self.emit("phase", {"phase": phase, **data, "allowed": list(self.snapshot.allowed)})
        run = self.current_run
        if run is not None and run.writer is not None and not run.writer.closed.is_set():
            extra = ", ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}" for k, v in data.items()
                              if k in ("baseline_s", "armed_timeout_s", "trigger_time_s", "fit_window_s"))
            run.log("phase", phase + (f" ({extra})" if extra else ""))

    def _message(self, text: str) -> None:
        self.emit("message", text)
        self._log("message", text)

    def make_fault(self, who: str, message: str, kind: str = "error", **extra) -> Fault:
        """A Fault naming the bench device of a role (``who``: a role or a device name)."""
        role = who if who in self.roles else ""
        device = self.roles.get(who, who)
        if message.startswith(f"{device}: "):  # driver errors name their device: once is enough
            message = message[len(device) + 2:]
        return Fault(device, message, kind, role, **extra)

    def emit_valve(self, st) -> None:
        self.note_valve(st)
        self.emit("valve", valve_event(self.roles.get("valve", "valve"), st))

    def note_valve(self, st) -> None:
        """On the control thread (the slow channels' polls arrive as messages): the valve's last state."""
        self._valve_state, self._valve_position = st.state, float(st.position.value)
        snap = self.snapshot
        self._publish(snap.phase, snap.data)  # arm may have become possible, or not

    @property
    def valve_open(self) -> bool | None:
        """From the last actuator status the engine read: open and idle/armed (None: not read yet)."""
        if self._valve_state is None:
            return None
        return self._valve_state in (ValveState.IDLE, ValveState.ARMED) and (self._valve_position or 0.0) >= 99.0

    def _log(self, kind: str, text: str) -> None:
        """An event into the current run's file, if one is open."""
        run = self.current_run
        if run is not None:
            run.log(kind, text)

    def _run_active(self) -> bool:
        return self.current_run is not None and self.current_run.active

    def _end(self, status: str, reason: str):
        """On the control thread: end the current run (idempotent; nothing to end: nothing done)."""
        return self.current_run.end(status, reason) if self.current_run is not None else None

    # ------------------------------------------------------------------ control thread
    def submit(self, fn: Callable[[], Any]) -> cf.Future:
        fut: cf.Future = cf.Future()
        if self._closing.is_set():
            fut.set_exception(VelabError("recorder is closed"))
            return fut
        self._cmds.put((fn, fut))
        return fut

    def _control_loop(self) -> None:
        while not self._closing.is_set():
            try:
                fn, fut = self._cmds.get(timeout=0.05)
            except queue.Empty:
                fn = fut = None
            if fn is not None and fut.set_running_or_notify_cancel():
                self._current_fut = fut
                try:
                    res = fn()
                    if res is not DEFER:
                        fut.set_result(res)
                except BaseException as exc:  # noqa: BLE001 - delivered through the future
                    fut.set_exception(exc)
                finally:
                    self._current_fut = None
            try:
                self._tick()
            except Exception as exc:  # noqa: BLE001 - a bug in a timer: end the run, say why
                log.exception("control tick")
                if self.current_run is not None:
                    self.current_run.request_end("failed", f"recorder error: {type(exc).__name__}: {exc}")

    def device_sleep(self, dt: float) -> None:
        """Wait dt seconds of device time (the simulation clock if there is one)."""
        if self.clock is not None and hasattr(self.clock, "sleep"):
            self.clock.sleep(dt)
        else:
            time.sleep(dt)

    # ------------------------------------------------------------------ commands
    def connect(self) -> cf.Future:
        """(Re)connect every device of the bench: phase connecting -> ready."""
        return self.submit(self._do_connect)

    def _do_arm(self):
        if self._run_active() or self.phase in (P.CONNECTING, P.FITTING):
            raise VelabError(f"cannot arm while {self.phase}")
        if not self._devices_ready():
            self._do_connect()
        self.current_run = Run(self)
        return self.current_run.arm()

    def _do_trigger(self):
        if self.current_run is None:
            raise VelabError(f"cannot trigger while {self.phase}" + (" (arm first)" if self.phase in
                                                                     (P.READY, P.DISCONNECTED) + P.END_PHASES else ""))
        return self.current_run.trigger(self._current_fut)

    def _tick(self) -> None:
        if self.current_run is not None:
            self.current_run.tick()

    def arm(self, settings: "RecordSettings | dict | None" = None) -> cf.Future:
        """Arm a run (connects first if needed); ``settings`` replace the current ones for this and the
        next runs. The valve must be open and idle: after a run, ``reset_valve()`` first."""
        if settings is None:
            return self.submit(self._do_arm)

        def arm_with():
            self._set_settings(settings)
            return self._do_arm()
        return self.submit(arm_with)

    def trigger(self) -> cf.Future:
        """Trigger the manoeuvre. While the baseline is still filling the trigger is queued (a
        ``trigger`` event with queued=True) and carried out as soon as it can be; the Future then
        settles with the estimated trigger time, or with an error if the run ends first."""
        return self.submit(self._do_trigger)

    def stop(self) -> cf.Future:
        """End cleanly, keep the data (status stopped); the fit is kept if its window is in."""
        return self.submit(lambda: self._end(P.STOPPED, "stopped by the operator"))

    def abort(self, reason: str = "") -> cf.Future:
        """Valve to its safe state, end and mark the run (status aborted)."""
        return self.submit(lambda: self._end(P.ABORTED, reason or "aborted by the operator"))

    def halt(self) -> None:
        """Stop now: valve safe, file closed "aborted" (reason "halted"), no fit; returns within ~5 s."""
        run = self.current_run
        if run is not None:
            run.halt_ev.set()
            if run.fit is not None:
                run.fit.cancel()
        fut = self.submit(lambda: self._end(P.ABORTED, "halted"))
        try:
            fut.result(timeout=5.0)
        except Exception:  # noqa: BLE001 - halting never raises
            pass

    def reset_valve(self) -> cf.Future:
        """Reset the actuator (reopens the valve; clears a FAULT) and give the flow 1 s to settle.
        Refused while a run records; the Future's result is the valve's ValveStatus."""
        return self.submit(self._do_reset_valve)

    def predict_surge(self, beta_per_s=None, gamma=None):
        """Pure, no I/O: the interlock's prediction for the current settings."""
        s = self.settings
        if beta_per_s is not None or gamma is not None:
            s = s.with_changes(beta_per_s=beta_per_s if beta_per_s is not None else s.beta_per_s,
                               gamma=gamma if gamma is not None else s.gamma)
        return predict_surge(self.rig, s, self.current_run.steady if self.current_run is not None else None)

    def _set_settings(self, settings) -> None:
        if self._run_active():
            raise VelabError(f"cannot change the settings while {self.phase}")
        if isinstance(settings, dict):
            settings = RecordSettings.from_dict(settings)
        self.settings = settings

    # ------------------------------------------------------------------ connect
    def _devices_ready(self) -> bool:
        return bool(self.roles) and all(n in self.devices for n in self.roles.values())

    def _describe_valve(self, drv, name: str) -> str:
        st = drv.read_status()
        self.emit_valve(st)
        return f"{st.state.name}, {st.position.value:.1f} % open"

    def _describe_flowmeter(self, drv, name: str) -> str:
        r = drv.read_flow()
        return f"{r.value * 1e3:.3f} l/s ({r.quality.value})"

    def _describe_pressure(self, drv, name: str) -> str:
        return pressure_source(drv, name).describe()

    # what a connected device of each role says it is doing, for the connect report
    def _peer(self, name: str):
        """The driver of bench device ``name``, opened once (a fired valve's DAQ is the pressure source's)."""
        if name not in self.bench.devices:
            raise DeviceFailure(f"bench {self.bench.name!r}: no device {name!r} (have: {', '.join(self.bench.devices)})")
        if name not in self.devices:
            self.devices[name] = open_device(self.bench.devices[name], peers=self._peer)
        return self.devices[name]

    _DESCRIBE = {"valve": _describe_valve, "flowmeter": _describe_flowmeter, "pressure": _describe_pressure}

    def _do_connect(self) -> list[DeviceStatus]:
        if self._run_active():
            raise VelabError(f"cannot reconnect while {self.phase}")
        self.set_phase(P.CONNECTING)
        out = []
        try:
            self.roles = resolve_roles(self.bench)
            for role, name in self.roles.items():
                dev = self.bench.devices[name]
                if name not in self.devices:
                    try:
                        self.devices[name] = open_device(dev, peers=self._peer)
                    except (OSError,) + DEVICE_ERRORS as exc:
                        raise DeviceFailure(f"{name}: cannot connect: {exc}") from None
                drv = self.devices[name]
                try:
                    msg = self._DESCRIBE[role](self, drv, name)
                except DEVICE_ERRORS as exc:
                    raise DeviceFailure(f"{name} ({role}): {failed_how(exc)}: {exc}") from None
                self.identities[name] = identity(drv)
                self.profiles[name] = profile_contents(drv)
                out.append(DeviceStatus(name, dev.kind, role, True, msg, self.identities[name]))
        except BaseException as exc:
            self.set_phase(P.DISCONNECTED, reason=str(exc))
            raise
        self.set_phase(P.READY, devices=[{"name": d.name, "kind": d.kind, "role": d.role, "ok": d.ok,
                                           "message": d.message, "identity": d.identity} for d in out])
        return out

    # ------------------------------------------------------------------ valve reset
    def _do_reset_valve(self):
        if self._run_active() or self.phase in P.RUN_PHASES:
            raise VelabError(f"cannot reset the valve while {self.phase}: stop or abort the run first")
        if not self._devices_ready():
            self._do_connect()
        valve = self.devices[self.roles["valve"]]
        try:
            st = reopen_valve(valve, self.device_sleep)
            self.emit_valve(st)
        except DEVICE_ERRORS as exc:
            raise DeviceFailure(f"{self.roles.get('valve', 'valve')}: reset failed: {exc}") from None
        self._message(f"valve reopened: actuator {st.state.name}, {st.position.value:.1f} % open")
        if self.phase in P.END_PHASES:
            self.set_phase(self.phase, **self.phase_data)  # arm is possible again: say so
        return st

    def check_valve_ready(self) -> None:
        try:
            st = self.devices[self.roles["valve"]].read_status()
        except DEVICE_ERRORS as exc:
            raise DeviceFailure(f"{self.roles['valve']}: actuator {failed_how(exc)}: {exc}") from None
        self.emit_valve(st)
        check_valve_open(st)

    # ------------------------------------------------------------------ closing
    def wait(self, timeout: float | None = None) -> RunSummary:
        run = self.current_run
        if run is None or not run.done.wait(timeout):
            raise TimeoutError(f"run not finished within {timeout} s")
        return run.summary

    def _deadline(self, device_seconds: float) -> float:
        return device_seconds / max(1e-9, min(self.clock_scale, 1e6)) + 30.0

    def run(self, *, reset_valve: bool = False) -> RunSummary:
        """Blocking: connect, (reset the valve), arm, trigger (queued until the baseline is in), wait.

        A refusal raises RunRefused/SafetyError (exit 3); a device failure DeviceFailure (exit 5).
        """
        s = self.settings
        if not self._devices_ready():
            self.connect().result(timeout=120)
        if reset_valve:
            self.reset_valve().result(timeout=60)
        self.arm().result(timeout=120)
        try:
            self.trigger().result(timeout=self._deadline(s.armed_timeout(self.bench_armed_timeout_s)) + 30)
        except VelabError:
            run = self.current_run
            if run is None or (not run.done.is_set() and not run.finished.is_set()):
                raise
        return self.wait(self._deadline(s.duration_s + s.pretrigger_s) + 600.0)

    def close(self) -> None:
        """Stop anything running (status "stopped"), disconnect, stop an owned simulator."""
        if self._run_active():
            try:
                self.stop().result(timeout=60)
            except Exception:  # noqa: BLE001
                pass
        if self.current_run is not None and self.current_run.writer is not None:
            self.current_run.done.wait(60)
        self._closing.set()
        self._control.join(10.0)
        for d in self.devices.values():
            try:
                d.close()
            except Exception:  # noqa: BLE001 - closing must not raise
                log.debug("device close", exc_info=True)
        self.devices.clear()
        self.snapshot = EngineSnapshot(P.DISCONNECTED, MappingProxyType({}), P.allowed_commands(P.DISCONNECTED))
        if self._owns_sim and self.sim is not None:
            self.sim.stop()
            self.sim = None

    def __enter__(self) -> "Recorder":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
