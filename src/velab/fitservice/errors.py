"""How a fit submitted to the fit service ends when it gives no result: named exceptions.

Every Future of :class:`velab.fitservice.FitService` ends in a result or in one of these (or the
fit's own user error, a :class:`velab.errors.VelabError`, one line):

* :class:`FitCancelled` -- the fit was cancelled (a halt, a quick fit overtaken, the operator);
* :class:`FitWorkerDied` -- the process or cluster worker running it ended without answering
  (killed, out of memory, could not start, the scheduler lost); ``reason`` names which;
* :class:`FitFailed` -- the fit raised something that is not a user error, in a process of its own
  ("Type: message"; ``error`` holds the user error when it was one).

velab.fit_worker raises the same classes (its ``Cancelled`` and ``WorkerDied`` are these).
"""

from __future__ import annotations


class FitCancelled(Exception):
    """The fit was cancelled before it gave a result."""


class FitWorkerDied(RuntimeError):
    """The process (or Dask worker) running the fit ended without answering.

    ``reason``: "worker lost" (the process or worker died) or "scheduler lost" (the connection to the
    Dask scheduler went)."""

    def __init__(self, message: str = "", reason: str = "worker lost"):
        super().__init__(message)
        self.reason = reason

    def __reduce__(self):
        return (type(self), (str(self), self.reason))


class FitFailed(RuntimeError):
    """The fit raised in another process; the message is "Type: message". ``error`` is the exception
    itself when it was a user error that could travel back (a VelabError), else None."""

    def __init__(self, message: str = "", error: BaseException | None = None):
        super().__init__(message)
        self.error = error

    def __reduce__(self):
        return (type(self), (str(self), self.error))


class WorkerMismatch(FitFailed):
    """A Dask worker runs another velab than this client: its fit is not taken."""
