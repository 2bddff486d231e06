"""The worker-process backend: fits in velab's own fit processes (velab.fit_worker).

Each process is ``sys.executable`` at a lower priority (fit_worker.NICENESS), started ahead of the
fit (``start``) so that its imports are done when the fit is asked for, taken from and given back to
fit_worker's small pool of idle processes. A process runs one fit at a time: this backend keeps the
queue and hands the next request to a process as soon as one is idle, so a process that dies takes
only its own fit with it. The request is sent as it is and run by the same
:func:`velab.fitservice.execute.execute` there, so the result is the one this process would compute,
bit for bit.

Outcomes: a process that dies fails its fit with FitWorkerDied (the exit status) as soon as its pipe
closes; ``replace_dead`` then starts another for the next fits (a batch), or, off, fails every later
fit with FitWorkerDied too (the recorder: it fits in its own process instead, and says so). A cancel
ends the fit at its next model; ``kill=True`` ends its process at once. A fit's user error comes
back as itself (DataError, one line), any other error as FitFailed ("Type: message").
"""

from __future__ import annotations

import collections
import socket
import threading
import time

from velab import fit_worker
from velab.fitservice.errors import FitCancelled, FitFailed, FitWorkerDied
from velab.fitservice.future import FitFuture, settle
from velab.fitservice.request import FitProgress, FitRequest


class ProcessBackend:
    """Up to ``processes`` fit processes (module docstring). Thread-safe."""

    name = "process"

    def __init__(self, processes: int = 1, *, replace_dead: bool = True):
        if processes < 1:
            raise ValueError("a process backend needs one or more processes")
        self.size = processes
        self.replace_dead = replace_dead
        self._lock = threading.Lock()
        self._procs: list[fit_worker.FitProcess] = []
        self._queue: collections.deque = collections.deque()  # (FitFuture, progress sink), not yet sent
        self._running: dict[fit_worker.FitProcess, tuple[FitFuture, int]] = {}
        self._closed = False
        self._lost = ""  # why there is no process any more (replace_dead off)

    # ------------------------------------------------------------------ processes
    def start(self) -> None:
        """Start (or take from the pool) every process now; OSError if one cannot be started."""
        with self._lock:
            while len(self._procs) < self.size and not self._closed:
                self._procs.append(fit_worker.acquire())

    @property
    def alive(self) -> bool:
        """A process is running (or can be started: ``replace_dead``)."""
        with self._lock:
            if self._closed:
                return False
            if any(p.alive for p in self._procs):
                return True
            return self.replace_dead or not self._procs

    @property
    def pids(self) -> list[int]:
        with self._lock:
            return [p.pid for p in self._procs if p.alive]

    def running(self) -> list[tuple[int, FitRequest]]:
        """(pid, request) of every fit a process is computing now."""
        with self._lock:
            return [(p.pid, f.request) for p, (f, _) in self._running.items()]

    # ------------------------------------------------------------------ fits
    def submit(self, request: FitRequest, progress=None) -> FitFuture:
        fut = FitFuture(request)
        with self._lock:
            closed = self._closed
            if not closed:
                self._queue.append((fut, progress))
        if closed:
            settle(fut, exc=FitWorkerDied("the fit service is closed"))
            return fut
        fut.bind(lambda kill: self._cancel(fut, kill))
        self._dispatch()
        return fut

    def _idle_process(self):
        """An idle live process, a new one if there is room (under the lock), or None."""
        for p in self._procs:
            if p.alive and p not in self._running:
                return p
        dead = [p for p in self._procs if not p.alive]
        if dead and not self.replace_dead:
            return None
        for p in dead:
            self._procs.remove(p)
        if len(self._procs) < self.size:
            p = fit_worker.acquire()
            self._procs.append(p)
            return p
        return None

    def _dispatch(self) -> None:
        sent, failed = [], []
        with self._lock:
            while self._queue:
                fut, sink = self._queue[0]
                if fut.done():  # cancelled while it waited
                    self._queue.popleft()
                    continue
                try:
                    proc = self._idle_process()
                except OSError as exc:
                    self._lost = f"no fit process could be started ({exc})"
                    proc = None
                if proc is None:
                    if not any(p.alive for p in self._procs) and (not self.replace_dead or self._lost):
                        why = self._lost or next((p.ended for p in self._procs if p.ended), "the fit process ended")
                        failed = [(f, why) for f, _ in self._queue]
                        self._queue.clear()
                    break
                self._queue.popleft()
                job, inner = proc.submit("request", on_progress=self._relay(fut, sink), request=fut.request)
                self._running[proc] = (fut, job)
                fut.where = f"{socket.gethostname()}:{proc.pid}"
                fut._t0 = time.perf_counter()
                sent.append((proc, fut, inner))
        for fut, why in failed:
            settle(fut, exc=FitWorkerDied(why))
        for proc, fut, inner in sent:
            inner.add_done_callback(lambda f, proc=proc, fut=fut: self._finished(proc, fut, f))

    @staticmethod
    def _relay(fut: FitFuture, sink):
        if sink is None:
            return None
        label = fut.request.label

        def progress(done, total, name):
            if not fut.done():
                sink(FitProgress(int(done), int(total), str(name), label))
        return progress

    def _finished(self, proc, fut: FitFuture, inner) -> None:
        with self._lock:
            if self._running.get(proc, (None,))[0] is fut:
                del self._running[proc]
        fut.seconds = time.perf_counter() - getattr(fut, "_t0", time.perf_counter())
        exc = inner.exception()
        if exc is None:
            settle(fut, inner.result())
        elif isinstance(exc, FitCancelled):
            settle(fut, exc=FitCancelled("fit cancelled"))
        elif isinstance(exc, FitWorkerDied):
            settle(fut, exc=FitWorkerDied(str(exc), "worker lost"))
        elif isinstance(exc, FitFailed) and exc.error is not None:
            settle(fut, exc=exc.error)  # the fit's user error, as the fitter raised it
        else:
            settle(fut, exc=exc)
        self._dispatch()

    def _cancel(self, fut: FitFuture, kill: bool) -> None:
        with self._lock:
            for i, (f, _) in enumerate(self._queue):
                if f is fut:
                    del self._queue[i]
                    return
            proc, job = next(((p, j) for p, (f, j) in self._running.items() if f is fut), (None, None))
        if proc is None:
            return
        if kill:
            proc.kill("cancelled")  # halt = stop now, not at the fit's next model
        else:
            proc.cancel(job)

    def close(self) -> None:
        """No more fits: queued ones end FitCancelled, the processes go back to fit_worker's pool (kept if
        idle, ended if they still compute: their fits end FitWorkerDied)."""
        with self._lock:
            self._closed = True
            queued = [f for f, _ in self._queue]
            self._queue.clear()
            procs, self._procs = self._procs, []
        for f in queued:
            settle(f, exc=FitCancelled("the fit service was closed"))
        for p in procs:
            fit_worker.release(p)
