"""The in-process backend: each fit on a thread of its own, in this process.

What the GUI's re-fit used to do on its thread pool and the recorder's online fit does when it has
no fit process: :func:`velab.fitservice.execute.execute` on a daemon thread. A cancelled fit's
Future ends at once with FitCancelled; its thread stops at the fit's next model (a thread cannot be
killed), and its late result is dropped.
"""

from __future__ import annotations

import logging
import threading
import time

from velab.fitservice.errors import FitCancelled
from velab.fitservice.execute import execute
from velab.fitservice.future import FitFuture, settle, this_process
from velab.fitservice.request import FitProgress, FitRequest

log = logging.getLogger(__name__)


def progress_relay(fut: FitFuture, sink):
    """The fit's progress(done, total, name): raises FitCancelled once the Future is being cancelled,
    else hands a FitProgress message to ``sink`` (a sink that raises is logged, never stops the fit)."""
    label = fut.request.label

    def progress(done, total, name=""):
        if fut.stopping:
            raise FitCancelled()
        if sink is not None:
            try:
                sink(FitProgress(int(done), int(total), str(name), label))
            except Exception:  # noqa: BLE001 - a consumer's bug never stops a fit
                log.exception("fit progress sink")
    return progress


class ThreadBackend:
    """Fits on threads of this process (module docstring). Thread-safe."""

    name = "thread"

    def submit(self, request: FitRequest, progress=None) -> FitFuture:
        fut = FitFuture(request)
        fut.where = this_process()
        fut.bind(lambda kill: None)  # the thread sees ``stopping`` at the fit's next model
        threading.Thread(target=self._run, args=(fut, progress), daemon=True,
                         name="velab-fit" + (f"-{request.label}" if request.label else "")).start()
        return fut

    @staticmethod
    def _run(fut: FitFuture, sink) -> None:
        t0 = time.perf_counter()
        try:
            result = execute(fut.request, progress_relay(fut, sink))
        except FitCancelled:
            fut.seconds = time.perf_counter() - t0
            settle(fut, exc=FitCancelled("fit cancelled"))
        except BaseException as exc:  # noqa: BLE001 - the Future carries it
            fut.seconds = time.perf_counter() - t0
            settle(fut, exc=exc)
        else:
            fut.seconds = time.perf_counter() - t0
            settle(fut, result)

    @property
    def alive(self) -> bool:
        return True

    def close(self) -> None:
        pass
