"""The Future of one fit (:class:`FitFuture`): a ``concurrent.futures.Future`` that can be cancelled
while it runs, and says where it ran."""

from __future__ import annotations

import os
import socket
import threading
from concurrent.futures import Future, InvalidStateError

from velab.fitservice.errors import FitCancelled


def this_process() -> str:
    """``host:pid`` of this process (a fit's ``where``)."""
    return f"{socket.gethostname()}:{os.getpid()}"


def settle(fut: Future, result=None, exc: BaseException | None = None) -> bool:
    """Set the outcome of ``fut`` unless it has one (a cancelled fit's late result is dropped); True if set."""
    try:
        if exc is not None:
            fut.set_exception(exc)
        else:
            fut.set_result(result)
    except InvalidStateError:
        return False
    return True


class FitFuture(Future):
    """The outcome of one :class:`~velab.fitservice.request.FitRequest`: its result, or a named exception
    (velab.fitservice.errors) or the fit's own user error.

    ``cancel()`` (= ``cancel_fit()``) ends the Future with :class:`FitCancelled` at once, pending or
    running; the fit itself stops at its next model (``kill=True``: a fit process is ended now, and with
    it any fit it runs). ``where`` names the process that ran it (``host:pid``), once known; ``seconds``
    its wall time, once it ended."""

    def __init__(self, request):
        super().__init__()
        self.request = request
        self.where = ""
        self.seconds: float | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._canceller = None  # the backend's: canceller(kill) stops the fit where it runs

    @property
    def stopping(self) -> bool:
        """A cancel was asked (the fit ends at its next model)."""
        return self._stop.is_set()

    def bind(self, canceller) -> None:
        """The backend's way to stop this fit where it runs (called by the backend)."""
        with self._lock:
            self._canceller = canceller
        if self._stop.is_set():
            canceller(False)

    def cancel_fit(self, kill: bool = False) -> bool:
        """End the fit (class docstring); False if it had already ended."""
        with self._lock:
            if self.done():
                return False
            self._stop.set()
            canceller = self._canceller
        settle(self, exc=FitCancelled(f"fit {self.request.label or ''} cancelled".replace("  ", " ")))
        if canceller is not None:
            canceller(kill)
        return True

    def cancel(self) -> bool:  # the Future verb: a named outcome (FitCancelled), also for a running fit
        return self.cancel_fit()
