"""How long a reader has listened to a device without data: the measure of a data timeout.

A reader loop (read with a short timeout, deliver what came, check the silence) adds each pass's duration,
at most ``cap_s``: a longer pass was the host keeping the reader from running (a loaded machine, a
collector's pause, another thread holding the interpreter), not the device keeping quiet -- a device that
sends meanwhile fills the port's buffer, read on the next pass. A loaded host's run failed "no valid frame
for 1 s" with 0 bytes discarded: the reader's read had returned empty and the reader then waited longer
than the timeout to run again. A silent device is still named after the timeout's worth of listening,
within seconds however loaded the host.
"""

from __future__ import annotations

import time
from typing import Callable

HELD_PASS_S = 0.25  # a pass counts at most max(this, 2 x the read's own wait)


class Silence:
    """The silence (s) a reader has listened to since the last data it delivered."""

    def __init__(self, cap_s: float, clock: Callable[[], float] = time.monotonic):
        self.cap_s, self._clock = cap_s, clock
        self.reset()

    @classmethod
    def for_wait(cls, wait_s: float) -> "Silence":
        """For a loop whose read waits at most ``wait_s`` for data."""
        return cls(max(HELD_PASS_S, 2.0 * wait_s))

    def reset(self) -> None:
        """Data came and was delivered (a slow consumer's time is not the device's silence)."""
        self.silent_s = 0.0
        self._mark = self._clock()

    def passed(self) -> float:
        """One pass of the read loop without data ended: the silence so far (s)."""
        now = self._clock()
        self.silent_s += min(max(0.0, now - self._mark), self.cap_s)
        self._mark = now
        return self.silent_s
