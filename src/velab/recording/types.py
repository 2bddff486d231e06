"""The plain data the engine publishes: events, faults, device statuses, run summaries; its errors."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from velab.drivers.base import DeviceError, DeviceException
from velab.errors import SafetyError, VelabError
from velab.recording.phases import exit_code


# what a device call can raise: the drivers' named errors, and (until every bad reply has its named
# exception in the drivers) the ValueError / IndexError a short or stale reply can still cause
DEVICE_ERRORS = (DeviceError, ValueError, IndexError)


def failed_how(exc: BaseException) -> str:
    """How a device call failed, in words: a device that answered with an exception reply "refused"; anything else
    (no reply, a reply that cannot be trusted, the link gone) "does not answer"."""
    return "refused" if isinstance(exc, DeviceException) else "does not answer"


class DeviceFailure(VelabError):
    """A device needed for the run does not answer or failed (exit 5)."""

    exit_code = 5


class RunRefused(SafetyError):
    """Readiness checks failed: nothing moved (exit 3)."""


@dataclass(frozen=True)
class RecorderEvent:
    """``kind``: phase, progress, samples, device, valve, trigger, fit, message, fault, done."""

    kind: str
    time_s: float  # host time (time.time())
    data: Any


FAULT_KINDS = ("no_response", "quality", "actuator_fault", "samples_lost", "storage", "error", "stuck", "protocol",
               "disconnected", "position_mismatch", "flow_mismatch")  # (the last two: velab.recording.redundancy)


class Fault(dict):
    """The data of a ``fault`` event: ``{"device", "role", "message", "kind", ...}``; ``str()`` is one line.

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


@dataclass(frozen=True)
class DeviceStatus:
    name: str
    kind: str
    role: str  # "pressure" | "valve" | "flowmeter"
    ok: bool
    message: str = ""
    identity: dict = field(default_factory=dict)


def _num(x):
    return None if x is None or (isinstance(x, float) and not math.isfinite(x)) else x


@dataclass
class RunSummary:
    path: Path | None
    status: str  # completed | completed-with-faults | stopped | aborted | failed | refused
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
    fit_latency_s: float | None = None  # from the fit window closing to the final result
    fit_error: str = ""
    faults: list = field(default_factory=list)  # one line per fault class seen (device: message)
    flagged_samples: int = 0  # pressure samples whose quality is not OK
    stroke: Any = None  # velab.recording.stroke.Stroke: the sigmoid of the measured valve position, if any

    @property
    def exit_code(self) -> int:
        return exit_code(self.status)

    def to_dict(self) -> dict:
        """Strict-JSON-ready (no NaN or infinity)."""
        d = {
            "path": str(self.path) if self.path else None, "status": self.status, "reason": self.reason,
            "exit_code": self.exit_code, "n_samples": self.n_samples, "lost_samples": self.lost_samples,
            "gaps": self.gaps, "flagged_samples": self.flagged_samples,
            "peak_head_m": None if not math.isfinite(self.peak_head_m) else round(self.peak_head_m, 4),
            "trigger_time_s": _num(self.trigger_time_s), "steady_head_m": _num(self.steady_head_m),
            "best_model": self.best_model, "wave_speed_m_s": _num(self.wave_speed_m_s),
            "fit_latency_s": _num(self.fit_latency_s), "fit_error": self.fit_error or None,
            "faults": list(self.faults),
            "stroke": self.stroke.to_dict() if self.stroke is not None else None,
        }
        if self.fit is not None:
            d["fit"] = self.fit.to_dict()
        return d


@dataclass(frozen=True)
class EngineSnapshot:
    """The engine's phase, its data (read-only) and the commands that can succeed now, as one value:
    readers on any thread see the three together (``Recorder.snapshot``)."""

    phase: str
    data: Any  # a read-only mapping (MappingProxyType)
    allowed: tuple


@dataclass(frozen=True)
class Hooks:
    """How a stage reports (explicit callables, no shared attributes):

    emit(kind, data)                 a live RecorderEvent
    log(kind, text)                  an event into the run file's event log
    fault(who, message, kind, **x)   a fault event (``who``: a role or a device name); it marks the run
    request_end(status, reason)      ask the engine to end the run (idempotent, from any thread)
    """

    emit: Any
    log: Any
    fault: Any
    request_end: Any


class RunHost(Protocol):
    """What a Run (velab.recording.run) asks of the recorder that armed it, and nothing more: the
    device session (read), the phase machine and the live events (on the control thread), and the
    control thread itself (``submit``). velab.recording.engine.Recorder is the one implementation."""

    rig: Any
    settings: Any
    bench: Any
    bench_where: str
    bench_armed_timeout_s: float | None
    clock_scale: float  # device seconds per host second (the simulated rig's clock; 1 at a real bench)
    sim: Any
    devices: dict
    roles: dict
    identities: dict
    profiles: dict
    last_stroke: Any  # the last measured stroke (velab.recording.stroke.Stroke) on this connection, or None

    @property
    def phase(self) -> str: ...
    @property
    def phase_data(self) -> Any: ...
    def emit(self, kind: str, data: Any) -> None: ...                      # a live RecorderEvent
    def set_phase(self, phase: str, **data) -> None: ...                   # publish a phase (control thread)
    def submit(self, fn) -> Any: ...                                       # run fn on the control thread
    def device_sleep(self, dt: float) -> None: ...                         # wait dt s of device time
    def make_fault(self, who: str, message: str, kind: str = "error", **extra) -> Fault: ...
    def emit_valve(self, st) -> None: ...                                  # a valve status read on the control thread
    def note_valve(self, st) -> None: ...                                  # the slow poll's valve status (control thread)
    def check_valve_ready(self) -> None: ...                               # reads the actuator: raises unless open and idle
