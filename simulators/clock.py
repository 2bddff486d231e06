"""Clocks for the simulated rig: one interface, a deterministic one for tests and a real-time one.

``now()`` is seconds on the simulation time axis (0 when the clock was made);
``sleep(dt)`` waits (real time) or advances (manual time); ``host_time(t)`` maps
a simulation time to host epoch seconds (time.time()), for readings' timestamps.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Protocol, runtime_checkable


@runtime_checkable
class Clock(Protocol):
    def now(self) -> float: ...
    def sleep(self, dt: float) -> None: ...
    def host_time(self, t: float) -> float: ...


class RealTimeClock:
    """Monotonic real time, starting at 0 (or ``start``) when created."""

    def __init__(self, start: float = 0.0):
        self._t0 = time.perf_counter() - start
        self._epoch0 = time.time() - start

    def now(self) -> float:
        return time.perf_counter() - self._t0

    def sleep(self, dt: float) -> None:
        if dt > 0:
            time.sleep(dt)

    def host_time(self, t: float) -> float:
        return self._epoch0 + t


class ManualClock:
    """Deterministic time for tests: it moves only when told (``advance``, ``set``, ``sleep``).

    ``sleep`` advances the clock at once, so code that waits on this clock runs as
    fast as possible. Thread-safe.
    """

    def __init__(self, start: float = 0.0, epoch: float = 1.7e9):
        self._t = float(start)
        self._epoch = epoch
        self._lock = threading.Lock()

    def now(self) -> float:
        with self._lock:
            return self._t

    def advance(self, dt: float) -> float:
        if dt < 0:
            raise ValueError("a clock cannot go backwards")
        with self._lock:
            self._t += dt
            return self._t

    def set(self, t: float) -> None:
        with self._lock:
            if t < self._t:
                raise ValueError(f"a clock cannot go backwards ({t} < {self._t})")
            self._t = float(t)

    def sleep(self, dt: float) -> None:
        if dt > 0:
            self.advance(dt)

    def host_time(self, t: float) -> float:
        return self._epoch + t


class ScaledClock:
    """Simulated time running ``scale`` times faster than real time (``scale=1``: real time).

    The ONE time base of a fast simulated rig: the valve's trigger instant, the ADC's
    sample clock and the flowmeter's refresh all read ``now()``, so a 24 s run takes
    24 / scale s of wall time while every device stays consistent with every other.
    ``sleep(dt)`` waits dt / scale real seconds. Thread-safe (no shared mutable state).
    """

    def __init__(self, scale: float = 1.0, start: float = 0.0):
        if not scale > 0:
            raise ValueError(f"clock scale must be positive, got {scale}")
        self.scale = float(scale)
        self._t0 = time.perf_counter()
        self._start = float(start)
        self._epoch0 = time.time() - start

    def now(self) -> float:
        return self._start + (time.perf_counter() - self._t0) * self.scale

    def sleep(self, dt: float) -> None:
        if dt > 0:
            time.sleep(dt / self.scale)

    def host_time(self, t: float) -> float:
        return self._epoch0 + t


def clock_scale(clock) -> float:
    """How many simulated seconds pass per real second (inf for a manual clock)."""
    if isinstance(clock, ManualClock):
        return float("inf")
    return float(getattr(clock, "scale", 1.0))


def buffer_scale(clock) -> float:
    """How many times the real device's buffer a simulated device holds (its FIFO, its ring): the clock's
    speed-up, so that the buffer holds the same *host* time as the real device (a test's speed-up must not turn
    a host's scheduling hiccup into an overrun the real bench would never see); 1 at real time, without a
    clock, and on a manual clock (time moves only when a test advances it: overruns are tested there)."""
    scale = clock_scale(clock)
    return 1.0 if math.isinf(scale) else max(1.0, scale)


def make_clock(kind: str = "realtime") -> Clock:
    """'realtime', 'manual', 'fast' (x12) or 'scaled:K' (K x real time)."""
    if kind == "realtime":
        return RealTimeClock()
    if kind == "manual":
        return ManualClock()
    if kind == "fast":
        return ScaledClock(FAST_SCALE)
    if isinstance(kind, str) and kind.startswith("scaled:"):
        try:
            return ScaledClock(float(kind.split(":", 1)[1]))
        except ValueError:
            pass
    raise ValueError(f"clock must be 'realtime', 'manual', 'fast' or 'scaled:K', got {kind!r}")


FAST_SCALE = 12.0
