"""Faults at any instant of a run: the instants a simulated rig observes, and a schedule of faults.

The simulated devices see two instants of a run, on the simulation clock's axis:
**arm** (the valve actuator received ARM) and **trigger** (it received TRIGGER);
**start** is when the simulation started and **now** (API only) when the fault is
scheduled. A fault is scheduled at ``"<anchor>[+<seconds>]"`` with an optional
duration; without one it lasts until cleared::

    [[faults.schedule]]
    device = "pressure_adc"            # a simulated device, or "rig" (model faults)
    fault = { silent = true }          # fault names of that device kind (FAULT_KEYS)
    at = "trigger+1.5"                 # start | arm | trigger [+ s]; a number = start + s
    duration_s = 0.5                   # optional
    every = false                      # true: at every arm/trigger (campaigns), not only the next one

    sim.schedule_fault("pressure_adc", at="trigger+1.5", duration_s=0.5, silent=True)

An anchored fault fires once, at the first such instant at or after it was
scheduled, unless ``every`` is true.
"""

from __future__ import annotations

import itertools
import math
import re
import threading
from dataclasses import dataclass, field

from velab.errors import ConfigError

ANCHORS = ("start", "arm", "trigger", "now")
_EPS = 1e-9  # s: boundaries of fault windows are this much early (float rounding of instants)


def _bool(v):
    return None if isinstance(v, bool) else "must be true or false"


def _int(lo, hi=None):
    def check(v):
        if isinstance(v, bool) or not isinstance(v, int) or v < lo or (hi is not None and v > hi):
            return f"must be an integer {lo}..{hi}" if hi is not None else f"must be an integer >= {lo}"
        return None

    return check


def _number(lo=None):
    def check(v):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or math.isnan(v) or (lo is not None and v < lo):
            return "must be a number" + (f" >= {lo}" if lo is not None else "")
        return None

    return check


def _channel_table(v):
    if not isinstance(v, dict) or not v:
        return "must be a table {channel = mA} (channels 0..3; nan allowed)"
    for k, mA in v.items():
        try:
            ch = int(k)
        except (TypeError, ValueError):
            return f"channel {k!r} is not an integer"
        if not 0 <= ch <= 3:
            return f"channel {ch} is not 0..3"
        if isinstance(mA, bool) or not isinstance(mA, (int, float)):
            return f"channel {ch}: {mA!r} is not a number of mA"
    return None


def _channel_list(v):
    if not isinstance(v, (list, tuple)) or not v or not all(isinstance(c, int) and not isinstance(c, bool)
                                                            and 0 <= c <= 3 for c in v):
        return "must be a list of channels 0..3"
    return None


# fault name -> check(value) -> error text or None, per device kind
def _exception_code(v):
    if isinstance(v, bool) or v not in (1, 2, 3, 4, 5, 6, 8, 10, 11):
        return "must be a Modbus exception code: 1, 2, 3, 4, 5, 6, 8, 10 or 11"
    return None


MODBUS_FAULTS = {
    "delay_s": _number(0), "exception_code": _exception_code, "corrupt_crc": _bool, "garble": _bool, "silent": _bool,
    "short_by": _int(1), "extra_bytes": _int(1), "wrong_unit": _bool, "disconnect": _bool, "count": _int(1),
    "drop_reply": _bool, "drop_request": _bool, "writes_only": _bool,
}
# Modbus faults that act on a reply, and can therefore also begin between a request and its reply
# (a fault anchored at the trigger instant hits the very reply to TRIGGER: the command was carried out)
MODBUS_REPLY_FAULTS = ("drop_reply", "silent", "disconnect", "corrupt_crc", "garble", "short_by", "extra_bytes",
                       "wrong_unit")
STREAM_FAULTS = {
    "silent": _bool, "corrupt": _bool, "corrupt_every": _int(1), "drop": _bool, "garbage": _bool, "disconnect": _bool,
}
RIG_FAULTS = {
    "channel_mA": _channel_table, "stuck_channels": _channel_list, "flow_nan": _bool, "flow_value": _number(),
    "flow_stuck": _bool, "flow_alarm_bits": _int(1, 0xFFFF), "valve_seize": _bool, "valve_fault_bits": _int(1, 0xFFFF),
}
FAULT_KEYS = {"modbus": MODBUS_FAULTS, "streaming_adc": STREAM_FAULTS, "rig": RIG_FAULTS}


def fault_family(kind: str) -> str:
    """The fault family of a device kind: 'rig', 'streaming_adc' or 'modbus'."""
    return kind if kind in ("rig", "streaming_adc") else "modbus"


def validate_fault(fault, family: str, where: str) -> dict:
    """A checked copy of a fault table; ConfigError (one line, naming ``where`` and the key) if not."""
    if not isinstance(fault, dict) or not fault:
        raise ConfigError(f"{where}: fault must be a non-empty table, e.g. {{ silent = true }}")
    known = FAULT_KEYS[family]
    out = {}
    for k, v in fault.items():
        if k not in known:
            raise ConfigError(f"{where}: fault {k!r} is not a {family} fault (known: {', '.join(sorted(known))})")
        msg = known[k](v)
        if msg:
            raise ConfigError(f"{where}: fault {k} = {v!r}: {msg}")
        if k == "channel_mA":
            v = {int(c): float(mA) for c, mA in v.items()}
        out[k] = v
    if not set(out) - {"count", "writes_only"}:
        raise ConfigError(f"{where}: count and writes_only only qualify a fault: name one (e.g. drop_reply = true)")
    if "valve_fault_bits" in out and not out.get("valve_seize"):
        raise ConfigError(f"{where}: valve_fault_bits needs valve_seize = true")
    return out


_INSTANT = re.compile(r"^\s*(start|arm|trigger|now)\s*(?:\+\s*((?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)\s*s?)?\s*$")


@dataclass(frozen=True)
class Instant:
    """``anchor`` (start / arm / trigger / abs) + ``offset_s`` >= 0; ``abs`` = a clock time (resolved "now")."""

    anchor: str
    offset_s: float = 0.0

    @classmethod
    def parse(cls, value, where: str = "at", now: float | None = None) -> "Instant":
        if isinstance(value, Instant):
            return value
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if not (value >= 0 and math.isfinite(value)):
                raise ConfigError(f"{where}: {value!r} must be a time >= 0 s after the start")
            return cls("start", float(value))
        m = _INSTANT.match(value) if isinstance(value, str) else None
        if not m:
            raise ConfigError(f"{where}: {value!r} is not an instant: use start, arm or trigger, "
                              f"optionally + seconds (\"trigger+1.5\"), or seconds after the start")
        anchor, off = m.group(1), float(m.group(2) or 0.0)
        if anchor == "now":
            if now is None:
                raise ConfigError(f"{where}: 'now' is only for faults scheduled at run time")
            return cls("abs", now + off)
        return cls(anchor, off)

    def __str__(self) -> str:
        if self.anchor == "abs":
            return f"t={self.offset_s:g} s"
        return self.anchor + (f"+{self.offset_s:g}" if self.offset_s else "")


class RunInstants:
    """The instants of a run the simulated devices observe (clock times), thread-safe."""

    def __init__(self, start: float = 0.0):
        self.start = float(start)
        self._events: dict[str, list[float]] = {"arm": [], "trigger": []}
        self._lock = threading.Lock()

    def mark(self, kind: str, t: float) -> None:
        with self._lock:
            self._events[kind].append(float(t))

    def clear(self, start: float | None = None) -> None:
        """Forget the arm and trigger instants (a new session on the same simulated rig; ``start``: its start)."""
        with self._lock:
            self._events = {"arm": [], "trigger": []}
            if start is not None:
                self.start = float(start)

    def times(self, kind: str) -> list[float]:
        if kind == "start":
            return [self.start]
        with self._lock:
            return list(self._events[kind])

    @property
    def last_arm(self) -> float | None:
        t = self.times("arm")
        return t[-1] if t else None

    @property
    def last_trigger(self) -> float | None:
        t = self.times("trigger")
        return t[-1] if t else None


_ids = itertools.count(1)


@dataclass(eq=False)
class ScheduledFault:
    """One fault of one device over a window of the run (see the module docstring)."""

    device: str
    fault: dict
    at: Instant
    duration_s: float | None = None
    every: bool = False
    created_s: float = 0.0  # clock time when scheduled: "once" anchors to the first instant at or after it
    id: int = field(default_factory=lambda: next(_ids))

    def __post_init__(self):
        self.remaining = self.fault.get("count")  # Modbus: applies to this many requests, then stops

    def starts(self, instants: RunInstants) -> list[float]:
        if self.at.anchor == "abs":
            return [self.at.offset_s]
        anchors = instants.times(self.at.anchor)
        if self.at.anchor != "start":
            anchors = [t for t in anchors if t >= self.created_s - 1e-9]
            if not self.every:
                anchors = anchors[:1]
        return [t + self.at.offset_s for t in anchors]

    def windows(self, instants: RunInstants) -> list[tuple[float, float]]:
        """[t0, t1) on the clock's axis, both ends moved 1 ns earlier: an instant computed another
        way (trigger + 0.2 + 0.1 vs trigger + 0.3) falls on the same side of a boundary."""
        end = math.inf if self.duration_s is None else self.duration_s
        return [(t0 - _EPS, t0 + end - _EPS) for t0 in self.starts(instants)]

    def active_at(self, t: float, instants: RunInstants) -> bool:
        return any(t0 <= t < t1 for t0, t1 in self.windows(instants))

    def describe(self) -> str:
        what = ", ".join(f"{k}={v}" for k, v in self.fault.items())
        dur = "" if self.duration_s is None else f" for {self.duration_s:g} s"
        return f"{self.device}: {what} at {self.at}{dur}" + (" (every run)" if self.every else "")


class FaultSchedule:
    """Every scheduled fault of a simulation; devices ask what is active at an instant."""

    def __init__(self, instants: RunInstants):
        self.instants = instants
        self._entries: list[ScheduledFault] = []
        self._lock = threading.Lock()

    def add(self, entry: ScheduledFault) -> ScheduledFault:
        with self._lock:
            self._entries.append(entry)
        return entry

    def remove(self, entry: ScheduledFault) -> None:
        with self._lock:
            if entry in self._entries:
                self._entries.remove(entry)

    def clear(self, device: str | None = None) -> None:
        with self._lock:
            self._entries = [e for e in self._entries if device is not None and e.device != device]

    def entries(self, device: str | None = None) -> list[ScheduledFault]:
        with self._lock:
            return [e for e in self._entries if device is None or e.device == device]

    def active(self, device: str, t: float) -> list[ScheduledFault]:
        return [e for e in self.entries(device) if e.active_at(t, self.instants)]

    def merged(self, device: str, t: float, consume: bool = False) -> dict:
        """The union of the faults active at t (later entries win); ``consume`` counts Modbus requests."""
        return merge_faults(self.take(device, t) if consume else self.active(device, t))

    def take(self, device: str, t: float, *, write: bool = False, exclude: frozenset = frozenset(),
             kinds: tuple | None = None) -> list[ScheduledFault]:
        """The entries that apply to one Modbus request at t, each counted once (``count``):
        ``writes_only`` entries only to a ``write``; entries in ``exclude`` (ids) not again; with
        ``kinds``, only entries with one of these faults."""
        out = []
        for e in self.active(device, t):
            if e.id in exclude or (e.fault.get("writes_only") and not write):
                continue
            if kinds is not None and not any(k in e.fault for k in kinds):
                continue
            if e.remaining is not None:
                with self._lock:
                    if e.remaining <= 0:
                        continue
                    e.remaining -= 1
            out.append(e)
        return out

    def windows(self, device: str, t_lo: float, t_hi: float) -> list[tuple[float, float, dict]]:
        """(t0, t1, fault) of every window of ``device`` that overlaps [t_lo, t_hi]."""
        out = []
        for e in self.entries(device):
            for t0, t1 in e.windows(self.instants):
                if t0 <= t_hi and t1 > t_lo:
                    out.append((t0, t1, e.fault))
        return out


def merge_faults(entries) -> dict:
    """One fault table from several entries (later entries win); the qualifiers (count, writes_only) dropped."""
    out: dict = {}
    for e in entries:
        out.update({k: v for k, v in e.fault.items() if k not in ("count", "writes_only")})
    return out


def parse_schedule(items, devices: dict[str, str], where: str = "[faults]") -> list[dict]:
    """Check ``[[faults.schedule]]`` tables; ``devices``: name -> kind. Returns keyword dicts for
    ``SimulatedBench.schedule_fault``. Every error is one line naming the entry and the key."""
    if not isinstance(items, list):
        raise ConfigError(f"{where}.schedule: must be an array of tables ([[faults.schedule]])")
    out = []
    keys = {"device", "fault", "at", "duration_s", "every"}
    for i, item in enumerate(items, 1):
        w = f"{where}.schedule #{i}"
        if not isinstance(item, dict):
            raise ConfigError(f"{w}: must be a table")
        unknown = sorted(set(item) - keys)
        if unknown:
            raise ConfigError(f"{w}: {unknown[0]}: unknown key (known: {', '.join(sorted(keys))})")
        for k in ("device", "fault", "at"):
            if k not in item:
                raise ConfigError(f"{w}: {k}: missing key")
        dev = item["device"]
        if dev not in devices:
            raise ConfigError(f"{w}: device: no simulated device {dev!r} (have: {', '.join(sorted(devices))}, rig)")
        fault = validate_fault(item["fault"], fault_family(devices[dev]), f"{w} ({dev})")
        at = Instant.parse(item["at"], f"{w}: at")
        dur = item.get("duration_s")
        if dur is not None and (isinstance(dur, bool) or not isinstance(dur, (int, float)) or not dur > 0
                                or not math.isfinite(dur)):
            raise ConfigError(f"{w}: duration_s = {dur!r}: must be a number > 0 (omit it: until cleared)")
        every = item.get("every", False)
        if not isinstance(every, bool):
            raise ConfigError(f"{w}: every = {every!r}: must be true or false")
        out.append({"device": dev, "fault": fault, "at": at, "duration_s": None if dur is None else float(dur),
                    "every": every})
    return out
