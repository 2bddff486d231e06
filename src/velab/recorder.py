"""The recording engine: run a water-hammer test, stream it into HDF5, fit it online.

One engine for ``velab record`` and the GUI (docs/recording.md)::

    rec = Recorder.simulated(RecordSettings(duration_s=22, out_dir=Path("runs")))
    summary = rec.run()            # connect, arm, baseline, trigger, record, final fit
    print(summary.best_model, summary.wave_speed_m_s, summary.path)
    rec.close()

Threads (none of them Qt):

* control thread: every device command and the slow-device polling (valve, flowmeter);
  commands (``connect``, ``arm``, ``trigger``, ``stop``, ``abort``) are queued to it and
  return ``concurrent.futures.Future``; the caller never blocks on device I/O;
* acquisition thread: pressure blocks from the ADC -> time axis, gaps, pressure
  ceiling, live events, fit buffer; hands writes to
* writer thread: the only one touching the run file (``velab.runfile.RunWriter``,
  SWMR), flushing at least every ``flush_interval_s``;
* fitter thread: intermediate fits on the growing window and the final fit as soon
  as the fit window's data are in.

Times: the run's time axis is the pressure ADC's sample clock, in seconds from the
*planned* trigger (sample ``round(pretrigger_s * rate)`` is t = 0); the trigger instant
actually measured from the valve-position feedback is ``/entry/manoeuvre/trigger_time``
on that axis. Every wait inside the engine runs on the device time base (the ADC's
samples, or the simulation clock), so a fast simulated clock makes a whole run fast.
"""

from __future__ import annotations

import concurrent.futures as cf
import datetime as _dt
import json
import math
import os
import queue
import shutil
import threading
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from velab.config import Manoeuvre, Rig
from velab.errors import SafetyError, VelabError

PHASES = ("idle", "connecting", "connected", "armed", "pretrigger", "transient", "fitting", "done", "stopped",
          "aborted", "failed")
EXIT_CODES = {"completed": 0, "refused": 3, "aborted": 4, "failed": 5, "stopped": 130}
BYTES_PER_SAMPLE = 60  # all fast channels of the run file, per sample, with chunk slack


class DeviceFailure(VelabError):
    """A device needed for the run does not answer or failed (exit 5)."""

    exit_code = 5


class RunRefused(SafetyError):
    """Readiness checks failed: nothing moved (exit 3)."""


# ============================================================================ data types


@dataclass(frozen=True)
class RecordSettings:
    """Everything an operator sets for one run; snapshot into the file (/entry/notes settings_json)."""

    duration_s: float = 30.0  # recorded after the trigger
    pretrigger_s: float = 2.0  # baseline before the trigger
    sample_rate_hz: float = 1000.0  # pressure ADC rate
    beta_per_s: float | None = None  # None -> the rig's manoeuvre
    gamma: float | None = None
    end_position_pct: float = 0.0
    out_dir: Path = Path("runs")
    title: str = ""
    operator: str = ""
    specimen: str = ""
    notes: str = ""
    fit: bool = True
    fit_models: tuple = (0, 1, 2, 3, 4, 5, 6)
    fit_window_s: float = 20.0
    fit_method: str = "auto"
    online_fit: bool = True  # fit as soon as the window is in (and publish intermediate fits)
    surge_margin: float = 0.1  # fraction added to the Joukowsky surge
    ceiling_head_m: float | None = None  # None -> 95 % of the limiting pressure, as head
    flow_tolerance: float = 0.05  # steady flow within this fraction of the rig's Q0, and stable
    flush_interval_s: float = 0.25
    # extensions
    fit_rate_hz: float = 1000.0  # the fit runs on data decimated (zero-phase FIR) to at most this rate
    intermediate_fits: bool = True
    run_number: int = 1
    head_range: tuple = (0.5, 1.5)  # steady head accepted as this range x the rig's steady head

    def __post_init__(self):
        object.__setattr__(self, "out_dir", Path(self.out_dir))
        object.__setattr__(self, "fit_models", tuple(int(m) for m in self.fit_models))
        for name in ("duration_s", "sample_rate_hz", "fit_window_s", "flush_interval_s", "fit_rate_hz"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and v > 0 and math.isfinite(v)):
                raise VelabError(f"{name} must be positive, got {v!r}")
        if not (self.pretrigger_s >= 0.05 and math.isfinite(self.pretrigger_s)):
            raise VelabError(f"pretrigger_s must be at least 0.05 s, got {self.pretrigger_s!r}")
        if not 0.0 <= self.end_position_pct < 100.0:
            raise VelabError(f"end_position_pct must be in [0, 100), got {self.end_position_pct!r}")
        if self.surge_margin < 0:
            raise VelabError(f"surge_margin must not be negative, got {self.surge_margin!r}")
        if self.flush_interval_s > 0.5:
            raise VelabError("flush_interval_s must be at most 0.5 s (crash safety)")
        if self.fit and self.fit_window_s > self.duration_s + 1e-9:
            raise VelabError(f"fit window {self.fit_window_s:g} s is longer than the record after the trigger "
                             f"({self.duration_s:g} s): lengthen --duration or shorten --window")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["out_dir"] = str(self.out_dir)
        return d

    def with_changes(self, **kw) -> "RecordSettings":
        return replace(self, **kw)


@dataclass(frozen=True)
class SurgePrediction:
    steady_head_m: float
    surge_m: float
    peak_head_m: float
    peak_pressure_pa: float
    limit_pa: float
    limiting: str  # "transducer full scale" | "pipe pressure rating"
    allowed: bool
    message: str


@dataclass(frozen=True)
class DeviceStatus:
    name: str
    kind: str
    role: str  # "pressure" | "valve" | "flowmeter" | "other"
    ok: bool
    message: str = ""


@dataclass(frozen=True)
class RecorderEvent:
    kind: str  # "phase", "samples", "device", "valve", "trigger", "fit", "message", "fault", "done"
    time_s: float  # host time (time.time())
    data: Any


FAULT_KINDS = ("no_response", "quality", "actuator_fault", "samples_lost", "storage", "error")


class Fault(dict):
    """The data of a ``fault`` event: ``{"device", "role", "message", "kind", ...}``; ``str()`` is one readable line.

    ``device`` is the bench device name (or "storage" / "recorder"), ``role`` its recorder role
    ("pressure", "valve", "flowmeter") or "", ``kind`` one of FAULT_KINDS, ``message`` the text
    without the device name; extra keys (e.g. ``quality``) depend on the kind.
    """

    def __init__(self, device: str, message: str, kind: str = "error", role: str = "", **extra):
        super().__init__(device=device, role=role, message=message, kind=kind, **extra)

    @property
    def device(self) -> str:
        return self["device"]

    @property
    def message(self) -> str:
        return self["message"]

    @property
    def kind(self) -> str:
        return self["kind"]

    def __str__(self) -> str:
        return f"{self['device']}: {self['message']}"


@dataclass
class RunSummary:
    path: Path | None
    status: str  # completed | stopped | aborted | failed | refused
    reason: str = ""
    n_samples: int = 0
    lost_samples: int = 0
    peak_head_m: float = float("nan")
    fit: Any = None  # SweepResult | None
    best_model: str | None = None
    wave_speed_m_s: float | None = None
    trigger_time_s: float | None = None
    steady_head_m: float | None = None
    gaps: int = 0
    fit_latency_s: float | None = None  # from the fit window closing (device time reached) to the final result
    fit_error: str = ""

    @property
    def exit_code(self) -> int:
        return EXIT_CODES.get(self.status, 5)

    def to_dict(self) -> dict:
        d = {
            "path": str(self.path) if self.path else None, "status": self.status, "reason": self.reason,
            "exit_code": self.exit_code, "n_samples": self.n_samples, "lost_samples": self.lost_samples,
            "gaps": self.gaps,
            "peak_head_m": None if not math.isfinite(self.peak_head_m) else round(self.peak_head_m, 4),
            "trigger_time_s": self.trigger_time_s, "steady_head_m": self.steady_head_m,
            "best_model": self.best_model, "wave_speed_m_s": self.wave_speed_m_s,
            "fit_latency_s": self.fit_latency_s, "fit_error": self.fit_error or None,
        }
        if self.fit is not None:
            d["fit"] = self.fit.to_dict()
        return d


# ============================================================================ helpers


def predict_surge(rig: Rig, settings: RecordSettings, steady_head_m: float | None = None) -> SurgePrediction:
    """Joukowsky surge a*dQ/(g A) over the steady head, plus margin, against the rig's limits."""
    from velab.drivers.base import GRAVITY_M_S2

    rho_g = rig.fluid.density_kg_m3 * GRAVITY_M_S2
    h0 = rig.steady_head_m if steady_head_m is None else max(float(steady_head_m), rig.steady_head_m)
    dq_frac = (100.0 - settings.end_position_pct) / 100.0
    surge = rig.joukowsky_head_m() * dq_frac * (1.0 + settings.surge_margin)
    peak = h0 + surge
    peak_pa = peak * rho_g
    limits = [(rig.transducer.full_scale_pa, "transducer full scale")]
    if rig.pipe.pressure_rating_pa is not None:
        limits.append((rig.pipe.pressure_rating_pa, "pipe pressure rating"))
    limit_pa, limiting = min(limits)
    allowed = peak_pa <= limit_pa
    verdict = "within" if allowed else "EXCEEDS"
    msg = (f"predicted peak {peak:.1f} m ({peak_pa / 1e5:.2f} bar) = steady {h0:.1f} m + Joukowsky surge "
           f"{surge:.1f} m (margin {settings.surge_margin:.0%}) {verdict} the {limiting} "
           f"({limit_pa / 1e5:.2f} bar = {limit_pa / rho_g:.1f} m)")
    if not allowed:
        msg = "manoeuvre refused: " + msg
    return SurgePrediction(h0, surge, peak, peak_pa, limit_pa, limiting, allowed, msg)


def ceiling_head(rig: Rig, settings: RecordSettings) -> float:
    if settings.ceiling_head_m is not None:
        return float(settings.ceiling_head_m)
    p = predict_surge(rig, settings)
    return 0.95 * p.limit_pa / (p.peak_pressure_pa / p.peak_head_m)


def check_output_dir(out_dir: Path, planned_bytes: int) -> None:
    """Refuse (RunRefused) a missing, unwritable or too-full output directory."""
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise RunRefused(f"{out_dir}: output directory does not exist")
    if not os.access(out_dir, os.W_OK | os.X_OK):
        raise RunRefused(f"{out_dir}: output directory is not writable")
    probe = out_dir / f".velab-write-test-{os.getpid()}"
    try:
        probe.write_bytes(b"x")
        probe.unlink()
    except OSError as exc:
        raise RunRefused(f"{out_dir}: output directory is not writable ({exc.strerror or exc})") from None
    free = shutil.disk_usage(out_dir).free
    need = 2 * planned_bytes + (16 << 20)
    if free < need:
        raise RunRefused(f"{out_dir}: too little free space for the planned run "
                         f"({free / 1e6:.1f} MB free, {need / 1e6:.1f} MB needed)")


def run_file_name(out_dir: Path, run_number: int) -> Path:
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    n = max(1, int(run_number))
    while True:
        p = Path(out_dir) / f"{stamp}_run{n:03d}.h5"
        if not p.exists():
            return p
        n += 1


def trigger_from_position(t: np.ndarray, pos_pct: np.ndarray, beta: float, gamma: float, end_pct: float) -> float | None:
    """The trigger instant from the measured valve opening (the commanded sigmoid, only t0 unknown).

    opening = end + (100 - end) / (1 + exp(beta (t - t0) + gamma)): from every sample
    between 10 % and 90 % of the stroke, t0 = t - (ln(100/p - 1) - gamma) / beta; median.
    """
    p = (np.asarray(pos_pct, dtype=float) - end_pct) / (100.0 - end_pct) * 100.0
    sel = np.isfinite(p) & (p > 10.0) & (p < 90.0)
    if sel.sum() < 3:
        return None
    y = np.log(100.0 / p[sel] - 1.0)
    return float(np.median(np.asarray(t, dtype=float)[sel] - (y - gamma) / beta))


class _Stop(Exception):
    pass


_h5py_hooks_installed = False


def _quiet_h5py_dealloc_errors() -> None:
    """After a storage failure h5py reports every handle of the unwritable file it cannot release
    (a traceback on stderr per object, from its destructors): the failure is reported once, as the run's
    status; these are dropped. Only exceptions raised inside h5py's own code are filtered."""
    import sys

    global _h5py_hooks_installed
    if _h5py_hooks_installed:
        return
    _h5py_hooks_installed = True
    prev_unraisable, prev_except = sys.unraisablehook, sys.excepthook

    def from_h5py(exc, tb, where="") -> bool:
        if "h5py" in where:
            return True
        while tb is not None:
            if "h5py" in tb.tb_frame.f_code.co_filename and tb.tb_next is None:
                return True
            tb = tb.tb_next
        return False

    def unraisable(u):
        if isinstance(u.exc_value, (RuntimeError, OSError)) and from_h5py(u.exc_value, u.exc_traceback,
                                                                        str(u.object or "") + str(u.err_msg or "")):
            return
        prev_unraisable(u)

    def excepthook(tp, value, tb):
        if isinstance(value, (RuntimeError, OSError)) and from_h5py(value, tb) and (
                "write failed" in str(value) or "ref count" in str(value) or "Unable to close" in str(value)):
            return
        prev_except(tp, value, tb)

    sys.unraisablehook = unraisable
    sys.excepthook = excepthook


# ============================================================================ the engine


class Recorder:
    """See the module docstring and docs/recording.md."""

    def __init__(self, bench, rig: Rig, settings: RecordSettings, *, sim=None, owns_sim: bool = False):
        self.bench = bench
        self.rig = rig
        self.settings = settings
        self.sim = sim
        self._owns_sim = owns_sim
        self.clock = getattr(sim, "clock", None)
        self.events: queue.Queue = queue.Queue(maxsize=1000)  # bounded: memory stays flat without a consumer
        self.events_dropped = 0
        self._listeners: list[Callable[[RecorderEvent], None]] = []
        self.phase = "idle"
        self.devices: dict[str, Any] = {}
        self.roles: dict[str, str] = {}
        self._cmds: queue.Queue = queue.Queue()
        self._valve_state = None
        self._valve_position: float | None = None
        self._closing = threading.Event()
        self._lock = threading.RLock()
        self._done = threading.Event()
        self._summary: RunSummary | None = None
        self._control = threading.Thread(target=self._control_loop, name="velab-recorder-control", daemon=True)
        self._control.start()
        self._reset_run_state()

    # ------------------------------------------------------------------ construction
    @classmethod
    def simulated(cls, settings: RecordSettings, sim_config: str = "default", material: str | None = None,
                  clock="realtime", rig: Rig | None = None) -> "Recorder":
        """Start the simulated rig in-process (ephemeral endpoints) and record from it; the Recorder owns it.

        ``clock``: "realtime", "fast" (12 x real time), "scaled:K", or a clock object.
        """
        from velab.simulators.bench import SimulatedBench, load_sim_config
        from velab.simulators.clock import make_clock

        path, doc = load_sim_config(sim_config)
        doc = dict(doc)
        if material:
            doc["material"] = material
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

    def _reset_run_state(self) -> None:
        s = self.settings
        self.path: Path | None = None
        self._writer = None
        self._wq: queue.Queue | None = None
        self._fs = float(s.sample_rate_hz)
        self._n_pre = int(round(s.pretrigger_s * self._fs))
        self._gidx = 0  # global sample index of the next sample (gaps included)
        self._n_written = 0
        self._lost = 0
        self._gaps = 0
        self._peak = -math.inf
        self._pre_sum = 0.0
        self._pre_n = 0
        self._steady: float | None = None
        self._trig_cmd_idx: int | None = None
        self._trigger_time: float | None = None  # on the file's axis
        self._trigger_measured = False
        self._pos_t: list = []
        self._pos_v: list = []
        self._fit_t = None
        self._fit_h = None
        self._fit_n = 0
        self._fit_start_idx = 0
        self._fit_gap_at: float | None = None
        self._window_closed = False
        self._window_close_wall: float | None = None
        self._intermediate_next = 0
        self._fit_result = None
        self._fit_error = ""
        self._fit_thread: threading.Thread | None = None
        self._fit_busy = threading.Event()
        self._cancel_intermediate = threading.Event()
        self._fit_result_intermediate = None
        self._final_fit_started = False
        self._end_status: str | None = None
        self._end_reason = ""
        self._marks: list[str] = []
        self._acq_thread: threading.Thread | None = None
        self._writer_thread: threading.Thread | None = None
        self._acq_stop = threading.Event()
        self._finished = threading.Event()
        self._polling = False
        self._last_poll = 0.0
        self._flow_faults = 0
        self._storage_checked = 0.0
        self._done.clear()
        self._summary = None
        self._fit_latency = None
        self._storage_error = ""

    # ------------------------------------------------------------------ events
    def add_listener(self, fn: Callable[[RecorderEvent], None]) -> None:
        """fn(RecorderEvent), called from engine threads (keep it short, thread-safe)."""
        self._listeners.append(fn)

    def _emit(self, kind: str, data: Any) -> None:
        ev = RecorderEvent(kind, time.time(), data)
        try:
            self.events.put_nowait(ev)
        except queue.Full:
            if kind == "samples":
                self.events_dropped += 1
            else:  # make room: control events matter more than the oldest live samples
                try:
                    self.events.get_nowait()
                    self.events_dropped += 1
                except queue.Empty:
                    pass
                try:
                    self.events.put_nowait(ev)
                except queue.Full:
                    self.events_dropped += 1
        for fn in list(self._listeners):
            try:
                fn(ev)
            except Exception:  # a listener's bug never stops a recording
                pass

    def _set_phase(self, phase: str, **data) -> None:
        self.phase = phase
        self._emit("phase", {"phase": phase, **data})

    def _message(self, text: str) -> None:
        self._emit("message", text)
        self._log("message", text)

    def _fault(self, role_or_device: str, message: str, kind: str = "error", **extra) -> None:
        """A ``fault`` event with structured data (Fault) and a line in the run file's event log."""
        role = role_or_device if role_or_device in self.roles else ""
        device = self.roles.get(role_or_device, role_or_device)
        if message.startswith(f"{device}: "):  # driver errors name their device: once is enough
            message = message[len(device) + 2:]
        f = Fault(device, message, kind, role, **extra)
        self._emit("fault", f)
        self._log("fault", str(f))

    def _emit_valve(self, st) -> None:
        """A ``valve`` event from a ValveStatus: state, position, open (>= 99 % and IDLE/ARMED), faults."""
        from velab.drivers.valve import ValveState

        pos = float(st.position.value)
        self._valve_state = st.state
        self._valve_position = pos
        self._emit("valve", {"device": self.roles.get("valve", "valve"), "state": st.state.name,
                             "position_pct": pos, "faults": list(st.faults),
                             "open": st.state in (ValveState.IDLE, ValveState.ARMED) and pos >= 99.0})

    @property
    def valve_open(self) -> bool | None:
        """From the last actuator status the engine read: open and idle/armed (None: not read yet)."""
        from velab.drivers.valve import ValveState

        if self._valve_state is None:
            return None
        return self._valve_state in (ValveState.IDLE, ValveState.ARMED) and (self._valve_position or 0.0) >= 99.0

    def _log(self, kind: str, text: str) -> None:
        """Event into the run file (event log), if one is open."""
        if self._wq is not None:
            self._wq.put(("event", self._now_axis(), kind, text))

    def _now_axis(self) -> float:
        return (self._gidx - self._n_pre) / self._fs

    # ------------------------------------------------------------------ control thread
    def _submit(self, fn: Callable[[], Any]) -> cf.Future:
        fut: cf.Future = cf.Future()
        if self._closing.is_set():
            fut.set_exception(VelabError("recorder is closed"))
            return fut
        self._cmds.put((fn, fut))
        return fut

    def _control_loop(self) -> None:
        while not self._closing.is_set():
            try:
                item = self._cmds.get(timeout=0.05)
            except queue.Empty:
                item = None
            if item is not None:
                fn, fut = item
                if fut.set_running_or_notify_cancel():
                    try:
                        fut.set_result(fn())
                    except BaseException as exc:  # noqa: BLE001 - delivered through the future
                        fut.set_exception(exc)
            if self._polling and time.monotonic() - self._last_poll >= 0.15:
                self._last_poll = time.monotonic()
                try:
                    self._poll_slow()
                except Exception as exc:  # noqa: BLE001
                    self._fault("recorder", f"slow-device poll failed: {type(exc).__name__}: {exc}")

    def _sleep(self, dt: float) -> None:
        """Wait dt seconds of device time (the simulation clock if there is one)."""
        if self.clock is not None and hasattr(self.clock, "sleep"):
            self.clock.sleep(dt)
        else:
            time.sleep(dt)

    # ------------------------------------------------------------------ commands
    def connect(self) -> cf.Future:
        return self._submit(self._do_connect)

    def predict_surge(self, beta_per_s=None, gamma=None) -> SurgePrediction:
        """Pure, no I/O: the interlock's prediction for the current settings."""
        s = self.settings
        if beta_per_s is not None or gamma is not None:
            s = replace(s, beta_per_s=beta_per_s if beta_per_s is not None else s.beta_per_s,
                        gamma=gamma if gamma is not None else s.gamma)
        return predict_surge(self.rig, s, self._steady)

    def arm(self, settings: "RecordSettings | dict | None" = None) -> cf.Future:
        """Arm a run (connects first if needed). ``settings`` (RecordSettings or its keyword arguments)
        replace the current ones for this and the next runs, on the control thread; refused while a run is
        active. The valve must be open and idle: after a run, ``reset_valve()`` first."""
        if settings is None:
            return self._submit(self._do_arm)

        def arm_with():
            self._set_settings(settings)
            return self._do_arm()
        return self._submit(arm_with)

    def reset_valve(self) -> cf.Future:
        """Reset the actuator (reopens the valve; clears a FAULT) and give the flow 1 s to settle.

        On the control thread like arm/trigger; the Future's result is the valve's ValveStatus.
        Refused (VelabError) while a run is recording. Connects first if needed. After a run on
        the same connection this is what makes the next ``arm()`` possible.
        """
        return self._submit(self._do_reset_valve)

    def _run_active(self) -> bool:
        return self._writer is not None and not self._finished.is_set()

    def _set_settings(self, settings) -> None:
        if self._run_active():
            raise VelabError(f"cannot change the settings while {self.phase}")
        if isinstance(settings, dict):
            settings = RecordSettings(**settings)
        self.settings = settings

    def trigger(self) -> cf.Future:
        return self._submit(self._do_trigger)

    def stop(self) -> cf.Future:
        return self._submit(lambda: self._do_end("stopped", "stopped by the operator"))

    def abort(self, reason: str) -> cf.Future:
        return self._submit(lambda: self._do_end("aborted", reason or "aborted by the operator"))

    def halt(self) -> None:
        """Stop now: actuator abort, close the file "aborted", no fit."""
        self.settings = replace(self.settings, fit=False)
        fut = self._submit(lambda: self._do_end("aborted", "halted"))
        try:
            fut.result(timeout=5.0)
        except Exception:  # noqa: BLE001
            pass

    # ------------------------------------------------------------------ connect
    def _role_devices(self) -> dict[str, str]:
        b = self.bench
        rec = dict(getattr(b, "recorder", {}) or {})
        roles = {}
        src = rec.get("pressure_source")
        if src is None:
            for kind in ("streaming_adc", "modbus_adc"):
                found = b.of_kind(kind)
                if found:
                    src = found[0].name
                    break
        if src is None or src not in b.devices:
            raise DeviceFailure(f"bench {b.name!r}: no pressure source (a streaming_adc or modbus_adc device, "
                                "or [recorder] pressure_source)")
        roles["pressure"] = src
        for role, kind in (("valve", "valve_actuator"), ("flowmeter", "flowmeter")):
            name = rec.get(role)
            if name is None:
                found = b.of_kind(kind)
                name = found[0].name if found else None
            if name is None or name not in b.devices:
                raise DeviceFailure(f"bench {b.name!r}: no {role} device ({kind})")
            roles[role] = name
        return roles

    def _do_connect(self) -> list[DeviceStatus]:
        from velab.drivers.base import DeviceError
        from velab.drivers.bench import open_device

        self._set_phase("connecting")
        self.roles = self._role_devices()
        out = []
        try:
            for role, name in self.roles.items():
                dev = self.bench.devices[name]
                if name not in self.devices:
                    try:
                        self.devices[name] = open_device(dev)
                    except (DeviceError, OSError) as exc:
                        raise DeviceFailure(f"{name}: cannot connect: {exc}") from None
                drv = self.devices[name]
                try:
                    if dev.kind == "streaming_adc":
                        msg = drv.identify()
                    elif role == "valve":
                        st = drv.read_status()
                        msg = f"{st.state.name}, {st.position.value:.1f} % open"
                        self._emit_valve(st)
                    elif role == "flowmeter":
                        r = drv.read_flow()
                        msg = f"{r.value * 1e3:.3f} l/s ({r.quality.value})"
                    else:
                        msg = ", ".join(f"{k} {v.value:.4g} {v.units}" for k, v in drv.read_channels().items())
                except DeviceError as exc:
                    raise DeviceFailure(f"{name} ({role}): does not answer: {exc}") from None
                out.append(DeviceStatus(name, dev.kind, role, True, msg))
        except BaseException:
            self._set_phase("failed")
            raise
        self._set_phase("connected", devices=[asdict(d) for d in out])
        return out

    # ------------------------------------------------------------------ arm
    @property
    def _adc(self):
        return self.devices[self.roles["pressure"]]

    @property
    def _valve(self):
        return self.devices[self.roles["valve"]]

    @property
    def _flowmeter(self):
        return self.devices[self.roles["flowmeter"]]

    @property
    def _streaming(self) -> bool:
        return self.bench.devices[self.roles["pressure"]].kind == "streaming_adc"

    def _manoeuvre(self) -> tuple[float, float, float]:
        s, m = self.settings, self.rig.manoeuvre
        return (s.beta_per_s if s.beta_per_s is not None else m.beta_per_s,
                s.gamma if s.gamma is not None else m.gamma, s.end_position_pct)

    def _channels_of_adc(self) -> tuple[str, str | None]:
        """(pressure channel, valve-position channel or None) by units."""
        adc = self._adc
        if self._streaming:
            chans = [(c.name, c.calibration.units) for c in adc.profile.channels]
            enabled = list(adc.profile.enabled)
        else:
            chans = [(c.name, c.calibration.units) for c in adc.channels]
            enabled = [c[0] for c in chans]
        p = next((n for n, u in chans if u == "Pa" and n in enabled), None)
        v = next((n for n, u in chans if u == "%" and n in enabled), None)
        if p is None:
            raise DeviceFailure(f"{self.roles['pressure']}: no pressure channel (units Pa) is acquired")
        return p, v

    def _read_steady_head(self) -> tuple[float, str]:
        """A short look at the pressure before anything is armed: (mean head, quality)."""
        from velab.drivers.base import DeviceError, pressure_to_head_m

        adc = self._adc
        pch, _ = self._channels_of_adc()
        try:
            if self._streaming:
                adc.configure(self._fs, [pch], self._block_samples())
                adc.start()
                vals, q = [], "ok"
                try:
                    need = max(10, int(0.05 * self._fs))
                    deadline = time.monotonic() + 5.0
                    while sum(v.size for v in vals) < need and time.monotonic() < deadline:
                        b = adc.get_block(timeout=2.0)
                        vals.append(b.head_m(pch))
                        if b.quality[0].value != "ok":
                            q = b.quality[0].value
                finally:
                    adc.stop()
                h = np.concatenate(vals) if vals else np.array([np.nan])
                return float(np.nanmean(h)), q
            r = adc.read_pressure(pch)
            return float(pressure_to_head_m(r.value, adc.density_kg_m3)), r.quality.value
        except DeviceError as exc:
            raise DeviceFailure(f"{self.roles['pressure']}: pressure check failed: {exc}") from None

    def _block_samples(self) -> int:
        from velab.drivers.streaming_adc import MAX_BLOCK, auto_block

        scale = getattr(self.clock, "scale", 1.0) if self.clock is not None else 1.0
        return int(min(MAX_BLOCK, max(auto_block(self._fs, 2), auto_block(self._fs * scale, 2))))

    def _readiness(self) -> tuple[float, float]:
        """Devices answer, flow steady within tolerance, pressure in range, valve open. Returns (Q, head)."""
        from velab.drivers.base import DeviceError, Quality
        from velab.drivers.valve import ValveState

        s = self.settings
        q0 = self.rig.steady_flow_m3_s
        # the valve first: closed (after a run) explains a zero flow, and the remedy is a reset
        try:
            st = self._valve.read_status()
        except DeviceError as exc:
            raise DeviceFailure(f"{self.roles['valve']}: actuator does not answer: {exc}") from None
        self._emit_valve(st)
        if st.state is ValveState.FAULT or st.faults:
            raise RunRefused(f"valve actuator in FAULT ({', '.join(st.faults) or 'no bits'}): reset it first (reset_valve())")
        if st.state not in (ValveState.IDLE, ValveState.ARMED) or st.position.value < 99.0:
            raise RunRefused(f"valve not open and idle (state {st.state.name}, {st.position.value:.1f} % open): "
                             "reopen it first (Recorder.reset_valve(), the GUI's Reset valve)")
        flows = []
        for i in range(3):
            try:
                r = self._flowmeter.read_flow()
            except DeviceError as exc:
                raise DeviceFailure(f"{self.roles['flowmeter']}: flowmeter does not answer: {exc}") from None
            if r.quality is not Quality.OK:
                raise RunRefused(f"steady flow not ready: flowmeter reading {r.value!r} is {r.quality.value}")
            flows.append(r.value)
            if i < 2:
                self._sleep(0.5)
        q = float(np.mean(flows))
        if len(set(flows)) == 1 and flows[0] != 0.0:
            # the meter refreshes at 2 Hz with noise: three readings 0.5 s apart never repeat exactly
            raise RunRefused(f"steady flow not ready: the flowmeter reading is frozen at {flows[0] * 1e3:.4f} l/s "
                             "(stuck sensor or no refresh; check the meter)")
        if abs(q - q0) > s.flow_tolerance * q0:
            raise RunRefused(f"steady flow {q * 1e3:.3f} l/s is not within {s.flow_tolerance:.0%} of the rig's "
                             f"Q0 = {q0 * 1e3:.3f} l/s (set the downstream valve)")
        if (max(flows) - min(flows)) > s.flow_tolerance * q0:
            raise RunRefused(f"steady flow is not stable ({min(flows) * 1e3:.3f}..{max(flows) * 1e3:.3f} l/s)")
        head, quality = self._read_steady_head()
        lo, hi = (f * self.rig.steady_head_m for f in s.head_range)
        ceiling = ceiling_head(self.rig, s)
        if quality != "ok" or not math.isfinite(head):
            raise RunRefused(f"pressure not ready: transducer reading is {quality}")
        if not lo <= head <= hi or head >= ceiling:
            raise RunRefused(f"steady head {head:.2f} m is out of range ({lo:.1f}..{min(hi, ceiling):.1f} m)")
        return q, head

    def _do_arm(self) -> Path:
        from velab.drivers.base import DeviceError
        from velab.drivers.valve import ValveState
        from velab.runfile import HEAD, Channel, RunWriter

        if self.phase not in ("connected", "done", "stopped", "aborted", "failed") or self._run_active():
            if self.phase == "idle":
                self._do_connect()
            else:
                raise VelabError(f"cannot arm while {self.phase}")
        elif not self._devices_ready():
            self._do_connect()
        self._reset_run_state()
        s = self.settings
        beta, gamma, end = self._manoeuvre()
        try:
            # 1. the output directory (nothing has moved)
            planned = int((s.pretrigger_s + s.duration_s) * self._fs * BYTES_PER_SAMPLE)
            check_output_dir(s.out_dir, planned)
            # 2. the interlock (pure) before anything is asked of the valve
            pred = predict_surge(self.rig, s)
            if not pred.allowed:
                raise RunRefused(pred.message)
            # 3. readiness
            q, head = self._readiness()
            self._steady = head
            pred = predict_surge(self.rig, s, head)
            if not pred.allowed:
                raise RunRefused(pred.message)
            ceiling = ceiling_head(self.rig, s)
            if pred.peak_head_m >= ceiling:
                self._emit("message", f"warning: predicted peak {pred.peak_head_m:.1f} m is above the pressure "
                                      f"ceiling {ceiling:.1f} m: the run will probably be aborted")
        except BaseException:
            self._set_phase("failed" if self.phase == "connecting" else "connected")
            raise
        # 4. the run file, created before the stream starts (sample 0 = first sample of the stream)
        pch, vch = self._channels_of_adc()
        self._pch, self._vch = pch, vch
        self._ceiling = ceiling
        inst = "instrument/pressure_transducer"
        channels = (
            HEAD,
            Channel("valve_position", "%", "f8", "measured valve opening (position feedback)", "instrument/valve"),
            Channel("pressure", "Pa", "f8", "gauge pressure at the transducer", inst),
            Channel("pressure_raw", "counts", "i4", "ADC counts of the pressure channel", inst),
            Channel("valve_position_raw", "counts", "i4", "ADC counts of the position channel", "instrument/valve"),
            Channel("sample_index", "samples", "i8", "device sample counter (gaps included)", "instrument/adc"),
            Channel("host_time", "s", "f8", "host epoch time of the sample (from the block's arrival)", "instrument/adc"),
        )
        slow = (Channel("flow", "m^3/s"), Channel("valve_state", "", "i4"), Channel("valve_opening", "%"))
        self.path = run_file_name(s.out_dir, s.run_number)
        device_setup = {"bench": self.bench.to_dict(), "roles": self.roles}
        if self.sim is not None:
            device_setup["simulator"] = {k: v for k, v in self.sim.config.items() if k != "devices"}
            device_setup["simulator"]["clock"] = type(self.clock).__name__
            device_setup["simulator"]["clock_scale"] = getattr(self.clock, "scale", 1.0)
        calibration = {}
        if self._streaming:
            for c in self._adc.profile.channels:
                calibration[c.name] = asdict(c.calibration) | {"range": c.range, "input": c.index}
        source = {"kind": "recording", "bench": self.bench.name,
                  "simulated": self.sim is not None,
                  "material": (self.sim.rig.material.name if self.sim is not None else None)}
        man = {"end_position": (end, "%"), "beta": (beta, "1/s"), "gamma": (gamma, ""),
               "planned_trigger_time": (0.0, "s"), "trigger_host_time": (float("nan"), "s"),
               "steady_head": (head, "m"), "measured_steady_flow": (q, "m^3/s"),
               "predicted_peak_head": (pred.peak_head_m, "m"), "ceiling_head": (ceiling, "m")}
        settings_snapshot = s.to_dict() | {"rig": self.rig.name}
        try:
            self._writer = RunWriter(
                self.path, self.rig, sample_rate_hz=self._fs, title=s.title or f"water-hammer run {self.path.stem}",
                channels=channels, slow_channels=slow,
                material=None, trigger_time_s=0.0, manoeuvre=man, device_setup=device_setup,
                settings=settings_snapshot, source=source, calibration=calibration, swmr=True,
                expected_samples=int((s.pretrigger_s + s.duration_s) * self._fs),
            )
        except VelabError as exc:
            self._set_phase("connected")
            raise RunRefused(str(exc)) from None
        self._wq = queue.Queue()
        self._writer_thread = threading.Thread(target=self._writer_loop, name="velab-recorder-writer", daemon=True)
        self._writer_thread.start()
        self._log("operator", f"armed by {s.operator or 'operator'}: {pred.message}")
        # 5. start the stream, then arm the actuator
        try:
            self._start_acquisition()
            self._valve.set_manoeuvre(beta, gamma, end)
            self._valve.arm()
            self._valve.wait_for({ValveState.ARMED}, timeout_s=5.0)
        except (DeviceError, DeviceFailure) as exc:
            self._finish("failed", f"arming failed: {exc}")
            raise DeviceFailure(f"arming failed: {exc}") from None
        self._polling = True
        self._log("operator", f"actuator armed: beta {beta:g} 1/s, gamma {gamma:g}, end {end:g} %")
        self._set_phase("armed", path=str(self.path))
        self._set_phase("pretrigger", path=str(self.path))
        return self.path

    # ------------------------------------------------------------------ acquisition
    def _start_acquisition(self) -> None:
        adc = self._adc
        chans = [self._pch] + ([self._vch] if self._vch else [])
        if self._streaming:
            adc.configure(self._fs, chans, self._block_samples())
            adc.start(wait_when_full=True)
        else:
            adc.stop_buffer()
            adc.configure_buffer(int(self._fs), len(chans))
            adc.start_buffer()
            self._fs = float(adc.sample_rate_hz or self._fs)
        self._acq_thread = threading.Thread(target=self._acq_loop, name="velab-recorder-acquisition", daemon=True)
        self._acq_thread.start()

    def _acq_loop(self) -> None:
        from velab.drivers.base import DeviceError, DeviceTimeout

        adc = self._adc
        timeouts = 0
        try:
            while not self._acq_stop.is_set():
                if self._streaming:
                    try:
                        blocks = [adc.get_block(timeout=0.2)] + adc.get_blocks()
                        timeouts = 0
                    except DeviceTimeout:
                        timeouts += 1
                        if not adc.running:
                            raise
                        continue
                else:
                    blocks = [adc.read_buffer()]
                    if blocks[0].n == 0:
                        time.sleep(0.01)
                        continue
                for b in blocks:
                    if b.n:
                        self._process_block(b)
                    if self._acq_stop.is_set():
                        break
        except DeviceError as exc:
            if not self._acq_stop.is_set():
                self._submit(lambda: self._do_end("failed", f"pressure acquisition failed: {exc}"))
        except Exception as exc:  # noqa: BLE001 - a bug: still close the run
            if not self._acq_stop.is_set():
                self._submit(lambda: self._do_end("failed", f"acquisition error: {type(exc).__name__}: {exc}"))

    def _process_block(self, b) -> None:
        s = self.settings
        fs = self._fs
        if b.lost_before:
            lost = int(b.lost_before)
            what = "estimated (reconnection)" if b.restarted else "exact"
            self._wq.put(("gap", self._n_written, lost))
            self._lost += lost
            self._gaps += 1
            self._gidx += lost
            note = f"{lost} samples lost before sample {self._gidx} ({what})"
            if b.restarted:
                note = "pressure ADC reconnected; " + note
            self._marks.append(note)
            self._fault("pressure", note, "samples_lost", lost=lost, restarted=bool(b.restarted))
            if self._trig_cmd_idx is not None and not self._window_closed and self._fit_gap_at is None:
                self._fit_gap_at = (self._gidx - lost - self._n_pre) / fs
        n = b.n
        g = self._gidx + np.arange(n)
        t = (g - self._n_pre) / fs
        if self._trigger_time is not None:
            t_end = self._trigger_time + s.duration_s
            keep = t < t_end - 0.5 / fs
            if not keep.all():
                k = int(keep.sum())
                b = _slice_block(b, k)
                n, g, t = k, g[:k], t[:k]
        if n == 0:
            self._maybe_finish_duration()
            return
        pi = b.channels.index(self._pch)
        head = b.head_m(self._pch)
        pos = b.column(self._vch) if self._vch and self._vch in b.channels else np.full(n, np.nan)
        pos_raw = b.raw_column(self._vch).astype(np.int32) if self._vch and self._vch in b.channels else np.zeros(n, np.int32)
        self._wq.put(("append", t, {
            "head": head, "valve_position": pos, "pressure": b.values[:, pi], "pressure_raw": b.raw[:, pi].astype(np.int32),
            "valve_position_raw": pos_raw, "sample_index": g, "host_time": b.host_times_s,
        }))
        self._n_written += n
        self._gidx += n
        with np.errstate(invalid="ignore"):
            mx = float(np.nanmax(head)) if np.isfinite(head).any() else -math.inf
        self._peak = max(self._peak, mx)
        # baseline (before the trigger command)
        if self._trig_cmd_idx is None:
            self._pre_sum += float(np.nansum(head))
            self._pre_n += int(np.isfinite(head).sum())
        else:
            self._collect_after_trigger(t, head, pos)
        self._emit("samples", {"time_s": t, "head_m": head, "valve_position": pos, "lost": int(b.lost_before)})
        # pressure ceiling (a suspender: abort the manoeuvre)
        ceiling = self._ceiling
        if mx > ceiling and self._end_status is None:
            self._end_status = "aborting"
            i = int(np.nanargmax(head))
            self._submit(lambda: self._do_end("aborted", f"pressure ceiling: head {mx:.2f} m > {ceiling:.2f} m "
                                                           f"at t = {t[i]:.3f} s"))
        self._maybe_finish_duration()

    def _collect_after_trigger(self, t, head, pos) -> None:
        s = self.settings
        beta, gamma, end = self._manoeuvre()
        if not self._trigger_measured and np.isfinite(pos).any():
            pn = (pos - end) / (100.0 - end) * 100.0
            sel = (pn > 10) & (pn < 90)
            if sel.any():
                self._pos_t.append(t[sel])
                self._pos_v.append(pos[sel])
            if (pn < 10).any() and self._pos_t:
                self._measure_trigger()
        if self._fit_t is not None:
            k = min(t.size, self._fit_t.size - self._fit_n)
            self._fit_t[self._fit_n:self._fit_n + k] = t[:k]
            self._fit_h[self._fit_n:self._fit_n + k] = head[:k]
            self._fit_n += k
        if self._trigger_time is None or not s.fit:
            return
        t_last = float(t[-1])
        after = t_last - self._trigger_time
        if not self._window_closed and after >= s.fit_window_s - 1.0 / self._fs:
            if not self._trigger_measured and self._pos_t:
                self._measure_trigger()
            self._window_closed = True
            self._window_close_wall = time.perf_counter()
            self._emit("message", f"fit window closed ({s.fit_window_s:g} s after the trigger)")
            if s.online_fit and self._end_status is None:
                self._start_fit(final=True)
        elif (s.online_fit and s.intermediate_fits and not self._window_closed and self._trigger_measured
              and not self._fit_busy.is_set()):
            fractions = (0.25, 0.5, 0.75)
            if self._intermediate_next < len(fractions) and after >= fractions[self._intermediate_next] * s.fit_window_s:
                w = fractions[self._intermediate_next] * s.fit_window_s
                self._intermediate_next += 1
                if self._fit_gap_at is None:
                    self._start_fit(final=False, window_s=w)

    def _measure_trigger(self) -> None:
        beta, gamma, end = self._manoeuvre()
        t0 = trigger_from_position(np.concatenate(self._pos_t), np.concatenate(self._pos_v), beta, gamma, end)
        self._trigger_measured = True
        if t0 is None:
            self._message("trigger instant: too few valve-position samples, keeping the command's estimate")
            return
        estimate = self._trigger_time
        self._trigger_time = t0
        self._wq.put(("trigger", t0))
        self._log("trigger", f"trigger instant measured from the valve position: t = {t0:.5f} s")
        self._emit("trigger", {"trigger_time_s": t0, "measured": True, "estimate_s": estimate})

    def _maybe_finish_duration(self) -> None:
        if self._trigger_time is None or self._end_status is not None:
            return
        if (self._gidx - self._n_pre) / self._fs >= self._trigger_time + self.settings.duration_s - 0.5 / self._fs:
            self._end_status = "completing"
            self._submit(lambda: self._do_end("completed", ""))

    # ------------------------------------------------------------------ writer thread
    def _writer_loop(self) -> None:
        w = self._writer
        last = time.monotonic()
        pending = 0
        interval = self.settings.flush_interval_s
        while True:
            try:
                op = self._wq.get(timeout=interval / 2)
            except queue.Empty:
                op = None
            try:
                if op is not None:
                    kind = op[0]
                    if kind == "close":
                        w.flush()
                        w.close(op[1], op[2])
                        return
                    if kind == "append":
                        w.append(op[1], **op[2])
                        pending += op[1].size
                    elif kind == "event":
                        w.event(op[1], op[2], op[3])
                    elif kind == "gap":
                        w.gap(op[1], op[2])
                    elif kind == "trigger":
                        w.set_trigger_time(op[1])
                    elif kind == "value":
                        w.set_value(op[1], op[2])
                    elif kind == "slow":
                        w.append_slow(op[1], op[2], op[3])
                now = time.monotonic()
                if now - last >= interval or pending >= 0.5 * self._fs:
                    room = self._storage_room()
                    if room is not None and room < self._storage_reserve():
                        # about to run out: end the run while the file can still be closed properly
                        self._storage_low(room)
                        return
                    w.flush()
                    last, pending = now, 0
            except Exception as exc:  # noqa: BLE001 - disk full, I/O error (h5py: OSError or RuntimeError)
                self._storage_failed(exc, op)
                return

    def _storage_reserve(self) -> int:
        """Room kept free for the rest of a flush interval and closing the file (HDF5 allocates in chunks)."""
        return (4 << 20) + 4 * int(0.5 * self._fs * BYTES_PER_SAMPLE)

    def _storage_room(self) -> int | None:
        """Bytes the run file can still grow by: free disk space, and the process's file-size limit."""
        try:
            room = shutil.disk_usage(self.path.parent).free
            try:
                import resource

                soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
                if soft != resource.RLIM_INFINITY:
                    room = min(room, soft - os.path.getsize(self.path))
            except (ImportError, OSError, ValueError):
                pass
            return int(room)
        except OSError:
            return None

    def _storage_low(self, room: int) -> None:
        """Stop before the disk is full: close the file cleanly (status failed) with every sample so far."""
        what = (f"disk full ({max(room, 0) / 1e6:.1f} MB left for the run file, "
                f"{self._storage_reserve() / 1e6:.1f} MB kept to close it): recording stopped")
        reason = f"storage failure: {what}"
        self._fault("storage", what, "storage", path=str(self.path), room_bytes=int(room))
        self._submit(lambda: self._do_end("failed", reason))
        while True:  # samples that arrive until the end request is handled are still written (room is kept)
            op = self._wq.get()
            try:
                if op[0] == "close":
                    self._writer.flush()
                    self._writer.close(op[1], op[2] if op[2] else reason)
                    return
                if op[0] == "append":
                    self._writer.append(op[1], **op[2])
                elif op[0] == "event":
                    self._writer.event(op[1], op[2], op[3])
                elif op[0] == "trigger":
                    self._writer.set_trigger_time(op[1])
                elif op[0] == "value":
                    self._writer.set_value(op[1], op[2])
                elif op[0] == "gap":
                    self._writer.gap(op[1], op[2])
                elif op[0] == "slow":
                    self._writer.append_slow(op[1], op[2], op[3])
            except Exception as exc:  # noqa: BLE001 - it filled up anyway
                self._storage_failed(exc, op, drained=op[0] == "close")
                return

    def _storage_failed(self, exc: BaseException, op, drained: bool = False) -> None:
        what = f"write failed (disk full?): {str(exc).splitlines()[0][:160]}"
        reason = f"storage failure: {what}"
        self._storage_error = reason
        _quiet_h5py_dealloc_errors()
        self._fault("storage", what, "storage", path=str(self.path))
        self._submit(lambda: self._do_end("failed", reason))
        if drained:
            try:
                self._writer._fh.close()
            except Exception:  # noqa: BLE001
                pass
            return
        # drain the queue until the close request, then close as well as possible
        while True:
            op = self._wq.get()
            if op[0] == "close":
                try:
                    self._writer.close(op[1], op[2] if op[2] else reason)
                except Exception:  # noqa: BLE001
                    try:
                        self._writer._fh.close()
                    except Exception:  # noqa: BLE001
                        pass
                return

    # ------------------------------------------------------------------ slow devices
    def _poll_slow(self) -> None:
        from velab.drivers.base import DeviceError, DeviceFault
        from velab.drivers.valve import ValveState

        readings = {}
        t = self._now_axis()
        try:
            st = self._valve.read_status()
            readings["valve_position"] = st.position
            self._emit_valve(st)
            if self._wq is not None:
                self._wq.put(("slow", "valve_state", t, int(st.state)))
                self._wq.put(("slow", "valve_opening", t, st.position.value))
            if st.state is ValveState.FAULT and self._end_status is None:
                self._end_status = "aborting"
                msg = f"valve actuator FAULT ({', '.join(st.faults) or 'no bits'}) at {st.position.value:.1f} % open"
                self._fault("valve", msg, "actuator_fault", faults=list(st.faults))
                self._submit(lambda: self._do_end("aborted", msg))
        except DeviceFault as exc:
            self._fault("valve", str(exc), "actuator_fault")
        except DeviceError as exc:
            self._fault("valve", f"valve actuator: {exc}", "no_response")
        try:
            r = self._flowmeter.read_flow()
            readings["flow"] = r
            if self._wq is not None:
                self._wq.put(("slow", "flow", t, r.value))
            if r.quality.value != "ok":
                self._flow_faults += 1
                if self._flow_faults in (1, 10, 100):
                    self._fault("flowmeter", f"flowmeter reading {r.quality.value}", "quality",
                                quality=r.quality.value)
        except DeviceError as exc:  # the pressure recording goes on
            self._flow_faults += 1
            if self._flow_faults in (1, 10, 100):
                self._fault("flowmeter", f"{exc} (pressure recording continues)", "no_response")
                if self._flow_faults == 1:
                    self._marks.append("flowmeter timeout during the run")
        if readings:
            self._emit("device", readings)

    # ------------------------------------------------------------------ trigger
    def _do_trigger(self) -> float:
        from velab.drivers.base import DeviceError

        if self.phase != "pretrigger":
            raise VelabError(f"cannot trigger while {self.phase} (arm first)")
        have = self._gidx
        if have < self._n_pre:
            raise VelabError(f"trigger refused: baseline not complete ({have / self._fs:.2f} of "
                             f"{self.settings.pretrigger_s:g} s recorded)")
        s = self.settings
        cap = int((s.fit_window_s + 2.0) * self._fs)
        self._fit_t = np.empty(cap)
        self._fit_h = np.empty(cap)
        self._fit_n = 0
        self._steady = self._pre_sum / self._pre_n if self._pre_n else self._steady
        idx = self._gidx
        try:
            self._valve.trigger()
        except DeviceError as exc:
            self._do_end("failed", f"trigger failed: {exc}")
            raise DeviceFailure(f"trigger failed: {exc}") from None
        self._trig_cmd_idx = idx
        t_est = (idx - self._n_pre) / self._fs
        self._trigger_time = t_est
        self._wq.put(("trigger", t_est))
        self._wq.put(("value", "manoeuvre/trigger_host_time", time.time()))
        self._log("operator", f"trigger commanded at about t = {t_est:.3f} s")
        self._set_phase("transient", trigger_time_s=t_est)
        self._emit("trigger", {"trigger_time_s": t_est, "measured": False})
        return t_est

    # ------------------------------------------------------------------ fits
    def _fit_data(self, window_s: float):
        s = self.settings
        n = self._fit_n
        t = self._fit_t[:n] - self._trigger_time
        h = self._fit_h[:n] - (self._steady or 0.0)
        dt = 1.0 / self._fs
        sel = (t >= -0.5 * dt) & (t < window_s - 0.5 * dt)
        t, h = t[sel], h[sel]
        q = max(1, int(self._fs // s.fit_rate_hz))
        if q > 1:
            from scipy.signal import decimate

            h = decimate(h, q, ftype="fir", zero_phase=True)
            t = t[::q][: h.size]
        return t, h

    def _fit_rig(self) -> Rig:
        beta, gamma, _ = self._manoeuvre()
        return self.rig.with_changes(manoeuvre=Manoeuvre(beta_per_s=beta, gamma=gamma))

    def _start_fit(self, final: bool, window_s: float | None = None) -> None:
        s = self.settings
        if final:
            if self._final_fit_started:
                return
            self._final_fit_started = True
        window = s.fit_window_s if window_s is None else window_s
        if final and self._fit_gap_at is not None:
            avail = self._fit_gap_at - self._trigger_time
            if avail < 2.0:
                self._fit_error = f"no fit: samples lost {avail:.2f} s after the trigger, inside the fit window"
                self._message(self._fit_error)
                return
            self._message(f"fit window shortened to {avail:.2f} s: samples lost inside it")
            window = math.floor(avail * self._fs) / self._fs
        try:
            t, h = self._fit_data(window)
        except Exception as exc:  # noqa: BLE001
            self._fit_error = f"fit data: {exc}"
            return
        if final:
            self._cancel_intermediate.set()  # the final fit gets the CPU
        else:
            self._cancel_intermediate.clear()
        self._fit_busy.set()
        # no warm start for the final fit: fit_sweep(initial=...) from a short-window fit was seen to
        # steer S3 into a worse minimum (S4 then wins by AIC); the final result must equal `velab fit`'s
        prev = getattr(self, "_fit_result_intermediate", None) if not final else None
        cancel = self._cancel_intermediate

        def progress(done, total, name):
            if not final and cancel.is_set():
                raise _Stop()

        def work():
            from velab.fitting import fit_sweep

            try:
                kw = {} if final else {"polish": False, "starts": 2}
                r = fit_sweep(t, h, self._fit_rig(), models=list(s.fit_models), window_s=window,
                              method=s.fit_method, initial=prev, progress=progress, **kw)
                if final:
                    self._fit_result = r
                    if self._window_close_wall is not None:
                        self._fit_latency = time.perf_counter() - self._window_close_wall
                elif self._fit_result is None:
                    pass
                if not final:
                    self._fit_result_intermediate = r
                self._emit("fit", {"result": r, "final": final, "window_s": window})
            except _Stop:
                pass
            except Exception as exc:  # noqa: BLE001
                if final:
                    self._fit_error = f"fit failed: {exc}"
                    self._message(self._fit_error)
            finally:
                self._fit_busy.clear()

        th = threading.Thread(target=work, name="velab-recorder-fit", daemon=True)
        if final:
            self._fit_thread = th
        th.start()

    # ------------------------------------------------------------------ ending
    def _safe_valve(self) -> None:
        from velab.drivers.base import DeviceError
        from velab.drivers.valve import ValveState

        try:
            st = self._valve.read_status().state
            if st is ValveState.ARMED:
                self._valve.abort()
                self._log("operator", "actuator: armed manoeuvre cancelled (abort)")
            elif st is ValveState.RUNNING:
                self._valve.abort()
                self._log("operator", "actuator: manoeuvre stopped where it is (abort)")
        except DeviceError as exc:
            self._fault("valve", f"actuator safe state: {exc}", "no_response")

    def _do_end(self, status: str, reason: str) -> RunSummary | None:
        """On the control thread: end the run with ``status`` (idempotent)."""
        from velab.drivers.base import DeviceError

        if self._finished.is_set() or self._writer is None:
            return self._summary
        if status != "completed":
            self._safe_valve()
        self._finish(status, reason)
        try:  # where the valve ended up (the GUI offers Reset valve when it is closed)
            self._emit_valve(self._valve.read_status())
        except (DeviceError, KeyError):
            pass
        return self._summary

    def _finish(self, status: str, reason: str) -> None:
        self._finished.set()
        self._polling = False
        self._end_status = status
        self._acq_stop.set()
        adc = self.devices.get(self.roles.get("pressure", ""))
        if adc is not None:
            try:
                if self._streaming:
                    adc.stop()
                else:
                    adc.stop_buffer()
            except Exception as exc:  # noqa: BLE001
                self._fault("pressure", f"pressure ADC stop: {exc}", "no_response")
        if self._acq_thread is not None and self._acq_thread is not threading.current_thread():
            self._acq_thread.join(5.0)
        if self._trigger_time is not None and not self._trigger_measured and self._pos_t:
            self._measure_trigger()
        marks = "; ".join(dict.fromkeys(self._marks))
        full_reason = "; ".join(x for x in (reason, marks) if x)
        if self._wq is not None:
            self._log("status", f"{status}: {full_reason}" if full_reason else status)
            self._wq.put(("close", status, full_reason[:255]))
            if self._writer_thread is not None:
                self._writer_thread.join(30.0)
        if self._storage_error and status != "failed":  # the file could not be written to the end
            status = "failed"
            full_reason = "; ".join(x for x in (self._storage_error, full_reason) if x)
            self._end_status = status
        fit_wanted = (self.settings.fit and status in ("completed", "stopped") and self._window_closed)
        if fit_wanted and not self._final_fit_started:
            self._start_fit(final=True)
        fit_wanted = fit_wanted and self._fit_thread is not None
        if fit_wanted:
            self._set_phase("fitting", status=status, reason=full_reason)
        elif status != "completed":
            self._set_phase(status, status=status, reason=full_reason)
        th = threading.Thread(target=self._conclude, args=(status, full_reason, fit_wanted), daemon=True,
                              name="velab-recorder-conclude")
        th.start()

    def _conclude(self, status: str, reason: str, fit_wanted: bool) -> None:
        fit = None
        if fit_wanted and self._fit_thread is not None:
            self._fit_thread.join()
            fit = self._fit_result
            if fit is not None and self.path is not None:
                try:
                    from velab.fitting.store import save_fit

                    save_fit(self.path, fit, name="online")
                except Exception as exc:  # noqa: BLE001
                    self._fit_error = f"fit not saved in the run file: {exc}"
                    self._emit("message", self._fit_error)
        summary = RunSummary(
            path=self.path, status=status, reason=reason, n_samples=self._n_written, lost_samples=self._lost,
            peak_head_m=self._peak if math.isfinite(self._peak) else float("nan"), fit=fit,
            best_model=fit.best.name if fit is not None else None,
            wave_speed_m_s=float(fit.best.wave_speed_m_s) if fit is not None else None,
            trigger_time_s=self._trigger_time, steady_head_m=self._steady, gaps=self._gaps,
            fit_latency_s=self._fit_latency if fit is not None else None, fit_error=self._fit_error,
        )
        self._summary = summary
        if status == "completed":
            self._set_phase("done", status=status, path=str(self.path))
        elif fit_wanted:
            self._set_phase(status, status=status, path=str(self.path))
        self._emit("done", summary)
        self._done.set()

    # ------------------------------------------------------------------ blocking conveniences
    def wait(self, timeout: float | None = None) -> RunSummary:
        if not self._done.wait(timeout):
            raise TimeoutError(f"run not finished within {timeout} s")
        return self._summary

    def _deadline(self, device_seconds: float) -> float:
        scale = getattr(self.clock, "scale", 1.0) if self.clock is not None else 1.0
        return device_seconds / max(1e-9, min(scale, 1e6)) + 30.0

    def run(self, *, reset_valve: bool = False) -> RunSummary:
        """Blocking: connect, arm, wait for the baseline, trigger, wait for the end, final fit.

        A refusal raises RunRefused/SafetyError (exit 3); a device failure DeviceFailure (exit 5).
        """
        s = self.settings
        if self.phase in ("idle", "failed") and not self.devices:
            self.connect().result(timeout=60)
        if reset_valve:
            self.reset_valve().result(timeout=30)
        self.arm().result(timeout=60)
        deadline = time.monotonic() + self._deadline(s.pretrigger_s)
        while self._gidx < self._n_pre and not self._finished.is_set():
            if time.monotonic() > deadline:
                self.abort("no pressure samples arrive (baseline)").result(timeout=30)
                break
            time.sleep(0.005)
        if not self._finished.is_set():
            try:
                self.trigger().result(timeout=30)
            except VelabError:
                if not self._finished.is_set():
                    raise
        return self.wait(self._deadline(s.duration_s + s.pretrigger_s) + 120.0)

    def _reset_valve(self):
        from velab.drivers.valve import ValveState

        st = self._valve.read_status()
        if st.state is not ValveState.IDLE or st.position.value < 99.0:
            self._valve.reset()
            st = self._valve.wait_for({ValveState.IDLE}, timeout_s=5.0)
            self._log("operator", "actuator reset (valve reopened)")
            self._emit_valve(st)
            self._sleep(1.0)  # let the flow settle
        else:
            self._emit_valve(st)
        return st

    def _do_reset_valve(self):
        from velab.drivers.base import DeviceError

        if self._run_active() or self.phase in ("armed", "pretrigger", "transient"):
            raise VelabError(f"cannot reset the valve while {self.phase}: stop or abort the run first")
        if not self._devices_ready():
            self._do_connect()
        try:
            st = self._reset_valve()
        except DeviceError as exc:
            raise DeviceFailure(f"{self.roles.get('valve', 'valve')}: reset failed: {exc}") from None
        self._message(f"valve reopened: actuator {st.state.name}, {st.position.value:.1f} % open")
        return st

    def _devices_ready(self) -> bool:
        return bool(self.roles) and all(n in self.devices for n in self.roles.values())

    def close(self) -> None:
        """Stop anything running (status "stopped"), disconnect, stop an owned simulator."""
        if self._writer is not None and not self._finished.is_set():
            try:
                self.stop().result(timeout=30)
                self._done.wait(60)
            except Exception:  # noqa: BLE001
                pass
        self._closing.set()
        self._control.join(5.0)
        for d in self.devices.values():
            try:
                d.close()
            except Exception:  # noqa: BLE001
                pass
        self.devices.clear()
        if self._owns_sim and self.sim is not None:
            self.sim.stop()
            self.sim = None

    def __enter__(self) -> "Recorder":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _slice_block(b, k: int):
    sq = None if b.sample_quality is None else b.sample_quality[:k]
    return replace(b, raw=b.raw[:k], signal=b.signal[:k], values=b.values[:k], sample_quality=sq,
                   host_time_s=b.host_time_s - (b.n - k) / b.rate_hz)


def settings_json(settings: RecordSettings) -> str:
    return json.dumps(settings.to_dict(), default=str)
