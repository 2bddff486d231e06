"""The fit in a process of its own: this module, run as ``__main__``, serves fit jobs over its pipes.

Why: the recorder's fit shares two cores with the acquisition, writer and GUI threads. In the
recorder's process the fit's Python-level work (the coarse stage: thousands of small evaluations)
takes turns with those threads for the interpreter lock; a process of its own, at a lower priority
(``NICENESS``), takes that contention away and can never starve the acquisition threads (what it
does to the latency is measured by benchmarks/online_fit_latency.py, docs/performance.md). The
child is ``sys.executable -c`` lowering its priority, then running this module (``_LAUNCH``), not
multiprocessing: a lab script without an ``if __name__ == "__main__"`` guard must not re-run itself.

Frames on the child's stdin/stdout: an 8-byte big-endian length, then a pickle (parent and child
are the same program of the same user).

    parent -> child   ("fit", job, call, kwargs)  fit_record(**kwargs) (call "record"; velab.fitting.entry)
                                               or the fit service's execute(request=FitRequest)
                                               ("request"; velab.fitservice)
                      ("cancel", job)          end that job at its next progress call
                      ("exit",)
    child -> parent   ("ready", pid)           imports done, the time-domain kernel loaded
                      ("progress", job, done, total, name)   after each model
                      ("done", job, result) | ("error", job, "Type: message", VelabError | None)
                      | ("cancelled", job)

The child's own stdout is sent to its stderr, which the parent logs (at debug level) and quotes
when the child dies. Every outcome is named: a child that dies (killed, out of memory) fails its
job with :class:`WorkerDied` and the exit status; the parent never waits on a dead child.
"""

from __future__ import annotations

import atexit
import collections
import logging
import os
import pickle
import queue
import struct
import subprocess
import sys
import threading
import weakref
from concurrent.futures import Future

from velab.errors import VelabError
from velab.fitservice.errors import FitCancelled, FitFailed, FitWorkerDied

log = logging.getLogger(__name__)

_HEADER = struct.Struct(">Q")
START_TIMEOUT_S = 60.0  # imports (numpy, scipy, numba) on a cold, loaded machine
KEEP_IDLE = 2  # idle workers kept for the next run (a recorder's campaign, the GUI's next run)


# the fit service's named outcomes (velab.fitservice.errors), by the names this module has always used
WorkerDied = FitWorkerDied  # the fit process ended without answering (killed, out of memory, could not start)
Cancelled = FitCancelled  # the job was cancelled (a halt, or a quick fit overtaken by the final one)


def _write(stream, lock: threading.Lock, msg) -> None:
    data = pickle.dumps(msg, protocol=pickle.HIGHEST_PROTOCOL)
    with lock:
        stream.write(_HEADER.pack(len(data)) + data)
        stream.flush()


def _read(stream):
    """One frame, or None at the end of the stream."""
    head = stream.read(_HEADER.size)
    if len(head) < _HEADER.size:
        return None
    (n,) = _HEADER.unpack(head)
    data = stream.read(n)
    if len(data) < n:
        return None
    return pickle.loads(data)


# --------------------------------------------------------------------------- the child
def _warm_up() -> None:
    """Load the time-domain kernel and the filters' (numba: compiled once, then from the disk cache) before the
    first job."""
    try:
        from velab import filters
        from velab.moc import warm_up

        warm_up()
        filters.warm_up()
    except Exception:  # noqa: BLE001 - a job that needs the kernel will say what is wrong
        log.debug("kernel warm-up failed", exc_info=True)


def serve(inp, out) -> int:
    """The child's loop: jobs one at a time; cancels read on a thread of their own."""
    from velab.fitservice.execute import execute  # the fit service's one call into the fitter
    from velab.fitting.entry import fit_record  # the one fit path

    calls = {"record": fit_record, "request": execute}

    _warm_up()
    lock = threading.Lock()
    jobs: queue.Queue = queue.Queue()
    cancelled: set = set()

    def reader() -> None:
        while True:
            msg = _read(inp)
            if msg is None or msg[0] == "exit":
                jobs.put(None)
                return
            if msg[0] == "cancel":
                cancelled.add(msg[1])
            else:
                jobs.put(msg)

    threading.Thread(target=reader, daemon=True, name="velab-fit-worker-reader").start()
    _write(out, lock, ("ready", os.getpid()))
    while True:
        msg = jobs.get()
        if msg is None:
            return 0
        _, job, call, kwargs = msg
        if job in cancelled:
            _write(out, lock, ("cancelled", job))
            continue

        def progress(done, total, name="", job=job):
            if job in cancelled:
                raise Cancelled()
            _write(out, lock, ("progress", job, int(done), int(total), str(name)))

        try:
            result = calls[call](progress=progress, **kwargs)
            reply = ("done", job, result)
        except Cancelled:
            reply = ("cancelled", job)
        except Exception as exc:  # noqa: BLE001 - the parent reports it as the fit's error
            reply = ("error", job, f"{type(exc).__name__}: {exc}", _travels(exc))
        cancelled.discard(job)
        _write(out, lock, reply)


def _travels(exc: BaseException):
    """A user error (VelabError) as it is, if it pickles (the parent raises it again: one line, its exit
    code); else None (the parent has its "Type: message")."""
    if not isinstance(exc, VelabError):
        return None
    try:
        pickle.dumps(exc, protocol=pickle.HIGHEST_PROTOCOL)
    except Exception:  # noqa: BLE001 - an attribute that does not pickle: the text goes alone
        return None
    return exc


def main() -> int:
    # frames go on a private copy of stdout; anything else the fit prints goes to stderr
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    return serve(sys.stdin.buffer, out)


# --------------------------------------------------------------------------- the parent
# The child lowers its priority before it imports anything: the recorder's acquisition and writer
# threads (and a GUI) come first on a busy machine, the fit takes what they leave (they need a
# fraction of a core; the fit's latency barely moves). Its start-up (imports, about 1 s of CPU) then
# never delays a trigger or a sample (it did, at the fast clock, before).
NICENESS = 5
_LAUNCH = ("import os, runpy\n"
           f"if hasattr(os, 'nice'):\n    os.nice({NICENESS})\n"
           "runpy.run_module('velab.fit_worker', run_name='__main__', alter_sys=True)\n")


class FitProcess:
    """One worker process; :meth:`submit` returns a Future of the SweepResult. Thread-safe."""

    def __init__(self):
        env = dict(os.environ)
        # the child imports velab as this process does (a checkout on sys.path, a test's tmp copy)
        paths = [p for p in sys.path if p and os.path.isdir(p)]
        env["PYTHONPATH"] = os.pathsep.join(paths + [env["PYTHONPATH"]] if env.get("PYTHONPATH") else paths)
        self._proc = subprocess.Popen([sys.executable, "-c", _LAUNCH], stdin=subprocess.PIPE,
                                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, close_fds=True,
                                      start_new_session=True)  # a Ctrl-C in the terminal is the parent's to handle
        self.pid = self._proc.pid
        _live.add(self)
        self._lock = threading.Lock()
        self._wlock = threading.Lock()
        self._jobs: dict[int, Future] = {}
        self._progress: dict[int, object] = {}  # job -> on_progress(done, total, name)
        self._next = 0
        self._dead: str | None = None
        self._ready = threading.Event()
        self._stderr: collections.deque[str] = collections.deque(maxlen=20)
        threading.Thread(target=self._read_replies, daemon=True, name="velab-fit-process-replies").start()
        threading.Thread(target=self._read_stderr, daemon=True, name="velab-fit-process-stderr").start()

    # ---------------------------------------------------------------- state
    @property
    def alive(self) -> bool:
        return self._dead is None and self._proc.poll() is None

    @property
    def ended(self) -> str:
        """Why the process is gone ("" while it runs)."""
        return self._dead or ("" if self._proc.poll() is None else f"the fit process ended ({self._exit_text()})")

    @property
    def busy(self) -> bool:
        with self._lock:
            return bool(self._jobs)

    def wait_ready(self, timeout: float = START_TIMEOUT_S) -> bool:
        return self._ready.wait(timeout) and self.alive

    # ---------------------------------------------------------------- jobs
    def submit(self, call: str = "record", *, on_progress=None, **kwargs) -> tuple[int, Future]:
        """Queue ``fit_record(**kwargs)`` (``call`` "record") or the fit service's ``execute(request=...)`` ("request"); (job id, Future). The Future fails with WorkerDied
        if the process dies, Cancelled if the job is cancelled, FitFailed (a RuntimeError: "Type:
        message", ``error`` the user error itself where it was one) with the fit's own error.
        ``on_progress(done, total, name)`` is called on the reply thread after each model."""
        fut: Future = Future()
        with self._lock:
            if self._dead is not None:
                fut.set_exception(WorkerDied(self._dead))
                return -1, fut
            self._next += 1
            job = self._next
            self._jobs[job] = fut
            if on_progress is not None:
                self._progress[job] = on_progress
        try:
            _write(self._proc.stdin, self._wlock, ("fit", job, call, kwargs))
        except (OSError, ValueError):
            self._died(f"the fit process could not be reached ({self._exit_text()})")
        return job, fut

    def cancel(self, job: int) -> None:
        try:
            _write(self._proc.stdin, self._wlock, ("cancel", job))
        except (OSError, ValueError):
            pass  # the reply reader names the outcome

    def kill(self, why: str = "killed") -> None:
        """End the process now; its jobs fail with WorkerDied(why)."""
        try:
            self._proc.kill()
        except OSError:
            pass
        self._died(why)

    def close(self, timeout: float = 2.0) -> None:
        """Ask the process to exit; kill it if it does not within ``timeout``."""
        try:
            _write(self._proc.stdin, self._wlock, ("exit",))
            self._proc.stdin.close()
        except (OSError, ValueError):
            pass
        try:
            self._proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait(5)
        self._died("closed")

    # ---------------------------------------------------------------- internals
    def _exit_text(self) -> str:
        rc = self._proc.poll()
        if rc is None:
            return "still running"
        if rc < 0:
            return f"killed by signal {-rc}"
        return f"exit status {rc}"

    def _died(self, why: str) -> None:
        with self._lock:
            if self._dead is None:
                self._dead = why
            jobs, self._jobs = self._jobs, {}
            self._progress.clear()
        self._ready.set()
        for fut in jobs.values():
            if not fut.done():
                fut.set_exception(WorkerDied(why))

    def _read_replies(self) -> None:
        out = self._proc.stdout
        while True:
            try:
                msg = _read(out)
            except Exception as exc:  # noqa: BLE001 - a reply that does not unpickle
                msg = None
                log.debug("bad reply from the fit process: %s", exc)
            if msg is None:
                break
            if msg[0] == "ready":
                self._ready.set()
                continue
            if msg[0] == "progress":
                with self._lock:
                    cb = self._progress.get(msg[1])
                if cb is not None:
                    try:
                        cb(*msg[2:5])
                    except Exception:  # noqa: BLE001 - a consumer's bug never stops the replies
                        log.exception("fit progress callback")
                continue
            with self._lock:
                fut = self._jobs.pop(msg[1], None)
                self._progress.pop(msg[1], None)
            if fut is None or fut.done():
                continue
            if msg[0] == "done":
                fut.set_result(msg[2])
            elif msg[0] == "cancelled":
                fut.set_exception(Cancelled())
            else:
                fut.set_exception(FitFailed(msg[2], msg[3] if len(msg) > 3 else None))
        try:
            self._proc.wait(5)
        except subprocess.TimeoutExpired:
            pass
        last = self._stderr[-1] if self._stderr else ""
        self._died(f"the fit process ended ({self._exit_text()})" + (f": {last}" if last else ""))

    def _read_stderr(self) -> None:
        for raw in self._proc.stderr:
            line = raw.decode("utf-8", "replace").rstrip()
            if line:
                self._stderr.append(line)
                log.debug("fit process %d: %s", self.pid, line)


# --------------------------------------------------------------------------- a small pool
_idle: list[FitProcess] = []
_live: "weakref.WeakSet[FitProcess]" = weakref.WeakSet()  # every worker started here, ended at exit
_pool_lock = threading.Lock()


def acquire() -> FitProcess:
    """An idle live worker (kept from an earlier run), else a new one (it starts in the background)."""
    with _pool_lock:
        while _idle:
            w = _idle.pop()
            if w.alive and not w.busy:
                return w
            w.kill("stale")
    return FitProcess()


def release(w: FitProcess) -> None:
    """Give a worker back: kept for the next run if it is alive and idle, else ended."""
    if not (w.alive and not w.busy):
        w.kill("released")
        return
    with _pool_lock:
        if len(_idle) < KEEP_IDLE:
            _idle.append(w)
            return
    w.close()


def shutdown() -> None:
    """End every worker of this process (at exit): idle ones asked to exit, busy ones killed."""
    with _pool_lock:
        idle, _idle[:] = list(_idle), []
    for w in idle:
        w.close(timeout=1.0)
    for w in list(_live):
        if w.alive:
            w.kill("exiting")


def _forget_in_child() -> None:
    # a forked child (a batch's worker) must not use or close the parent's pipes; the lock may have
    # been held at the fork
    global _pool_lock, _live
    _idle.clear()
    _live = weakref.WeakSet()
    _pool_lock = threading.Lock()


atexit.register(shutdown)
os.register_at_fork(after_in_child=_forget_in_child)


if __name__ == "__main__":
    sys.exit(main())
