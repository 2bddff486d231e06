"""The engine's outgoing events: a bounded queue that keeps what matters when nobody drains it.

Live data (samples, progress, device readings) are dropped first: a full queue refuses a live
event, and makes room for any other (a phase, a fault, a fit, the summary) by dropping the oldest
live one (the oldest event if there is none). Its own lock guards the buffer and the count of
dropped events; consumers use the ``queue.Queue`` verbs (``get``, ``get_nowait``, ``empty``).
"""

from __future__ import annotations

import queue
import threading
from collections import deque

LIVE = ("samples", "progress", "device")


class EventQueue:
    def __init__(self, maxsize: int = 1000):
        self.maxsize = maxsize
        self._items: deque = deque()
        self._cond = threading.Condition()
        self._dropped = 0

    @property
    def dropped(self) -> int:
        with self._cond:
            return self._dropped

    def offer(self, ev) -> None:
        """Queue ``ev``; when full, drop a live event (this one, if it is live) and count it."""
        with self._cond:
            if len(self._items) >= self.maxsize:
                self._dropped += 1
                if ev.kind in LIVE:
                    return
                i = next((i for i, old in enumerate(self._items) if old.kind in LIVE), 0)
                del self._items[i]
            self._items.append(ev)
            self._cond.notify()

    def put_nowait(self, ev) -> None:
        with self._cond:
            if len(self._items) >= self.maxsize:
                raise queue.Full
            self._items.append(ev)
            self._cond.notify()

    def get(self, timeout: float | None = None):
        with self._cond:
            if not self._cond.wait_for(lambda: self._items, timeout):
                raise queue.Empty
            return self._items.popleft()

    def get_nowait(self):
        with self._cond:
            if not self._items:
                raise queue.Empty
            return self._items.popleft()

    def empty(self) -> bool:
        with self._cond:
            return not self._items

    def qsize(self) -> int:
        with self._cond:
            return len(self._items)
