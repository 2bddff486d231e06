"""Clocks for the simulated rig: one interface, a deterministic one for tests and a real-time one.

``now()`` is seconds on the simulation time axis (0 when the clock was made);
``sleep(dt)`` waits (real time) or advances (manual time); ``host_time(t)`` maps
a simulation time to host epoch seconds (time.time()), for readings' timestamps.
"""

from __future__ import annotations

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


def make_clock(kind: str = "realtime") -> Clock:
    if kind == "realtime":
        return RealTimeClock()
    if kind == "manual":
        return ManualClock()
    raise ValueError(f"clock must be 'realtime' or 'manual', got {kind!r}")
