"""Read catalogue rows in worker processes, each file under a deadline.

Some damage makes the HDF5 library loop forever or crash, and h5py holds the
interpreter while it is inside the library (docs/run-format.md, "Damaged files"),
so the rows are read in child processes: a child that does not answer within
``deadline_s`` for one file is killed and the file is a ``damaged`` row with the
probe's reason; a child that dies likewise; a new child takes the rest.

A child reads many files (the reader's one-file probe would cost a Python start,
~0.3-1 s, per file). Children are forked from this process when it runs a single
thread (the command line: no imports to repeat), and started fresh
(``python -m velab.catalogue.extract``) otherwise (the GUI: a fork of a threaded
process could inherit a lock another thread holds). Either way they set
``VELAB_PROBE_CHILD`` (they are the probe) and never open a file for writing.
"""

from __future__ import annotations

import json
import os
import selectors
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from typing import Callable, Iterable, Iterator

DEADLINE_S = 10.0  # per file, as the reader's probe (velab.runfiles.probe.PROBE_TIMEOUT_S)
_STARTUP_S = 60.0  # a fresh child's imports on a loaded machine
_child_fds: set[int] = set()  # our ends of every child's pipes: a forked child closes its siblings'


def _serve(rfd: int, wfd: int) -> None:
    """Child side: one JSON path per line in, one JSON row per line out."""
    from velab.catalogue.rows import dumps, read_row

    os.environ["VELAB_PROBE_CHILD"] = "1"  # we are the probe: no grandchild per file
    with os.fdopen(rfd, "rb", buffering=0) as rin, os.fdopen(wfd, "wb", buffering=0) as wout:
        wout.write(b'"ready"\n')
        buf = b""
        while True:
            chunk = rin.read(65536)
            if not chunk:
                return
            buf += chunk
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                wout.write(dumps(read_row(json.loads(line))).encode() + b"\n")


class _Child:
    def __init__(self, fork: bool, preload: bool = True):
        self.pid = 0
        self.proc = None
        if fork:
            if preload:  # several children: imported once here, not in each; one child imports while we work on
                import velab.catalogue.rows  # noqa: F401
                import velab.runfiles.reader  # noqa: F401

            p_r, c_w = os.pipe()  # child -> parent
            c_r, p_w = os.pipe()  # parent -> child
            pid = os.fork()
            if pid == 0:  # pragma: no cover - runs in the child
                try:
                    for fd in _child_fds | {p_r, p_w}:
                        try:
                            os.close(fd)
                        except OSError:
                            pass
                    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
                    _serve(c_r, c_w)
                finally:
                    os._exit(0)
            os.close(c_w)
            os.close(c_r)
            self.pid, self.rfd, self.wfd = pid, p_r, p_w
        else:
            env = dict(os.environ, VELAB_PROBE_CHILD="1")
            self.proc = subprocess.Popen([sys.executable, "-m", "velab.catalogue.extract"], stdin=subprocess.PIPE,
                                         stdout=subprocess.PIPE, env=env, start_new_session=True)
            self.pid, self.rfd, self.wfd = self.proc.pid, self.proc.stdout.fileno(), self.proc.stdin.fileno()
        _child_fds.update((self.rfd, self.wfd))
        os.set_blocking(self.rfd, False)
        self.buf = b""
        self.ready = False
        self.path: str | None = None  # the file it is reading
        self.since = time.monotonic()

    def send(self, path: str) -> None:
        self.path, self.since = path, time.monotonic()
        os.write(self.wfd, json.dumps(path).encode() + b"\n")

    def lines(self) -> list[bytes] | None:
        """Complete lines read so far; None once the child closed its end (died)."""
        try:
            chunk = os.read(self.rfd, 1 << 20)
        except BlockingIOError:
            return []
        if not chunk:
            return None
        self.buf += chunk
        *done, self.buf = self.buf.split(b"\n")
        return done

    def close(self, kill: bool = False) -> int:
        """Stop the child; its exit status (negative: the signal)."""
        for fd in (self.wfd, self.rfd):
            _child_fds.discard(fd)
        if self.proc is not None:
            if kill:
                self.proc.kill()
            for f in (self.proc.stdin, self.proc.stdout):
                try:
                    f.close()
                except OSError:
                    pass
            try:
                return self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                return self.proc.wait()
        for fd in (self.wfd, self.rfd):
            try:
                os.close(fd)
            except OSError:
                pass
        if kill:
            try:
                os.kill(self.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        end = time.monotonic() + 5
        while True:
            pid, status = os.waitpid(self.pid, os.WNOHANG)
            if pid:
                return os.waitstatus_to_exitcode(status)
            if time.monotonic() > end:
                os.kill(self.pid, signal.SIGKILL)
                return os.waitstatus_to_exitcode(os.waitpid(self.pid, 0)[1])
            time.sleep(0.005)


def _can_fork() -> bool:
    return hasattr(os, "fork") and threading.active_count() == 1


def read_rows(paths: Iterable[str], jobs: int = 2, deadline_s: float = DEADLINE_S, fork: bool | None = None,
              stop: Callable[[], bool] | None = None, prime: bool = False) -> Iterator[dict | None]:
    """The row of every path, in the order they are read (not the order given).

    ``jobs`` child processes; ``fork``: None decides (fork only from a single-threaded
    process); ``stop()`` true ends the reading early (the GUI's folder changed).
    ``prime``: first yield None as soon as the children are started, so that the caller
    can do its own work while they import and read.
    """
    from velab.catalogue.rows import empty_row

    todo = deque(paths)
    if not todo:
        return
    fork = _can_fork() if fork is None else fork and hasattr(os, "fork")
    jobs = max(1, min(int(jobs), len(todo)))
    sel = selectors.DefaultSelector()
    children: list[_Child] = []

    def start() -> None:
        c = _Child(fork, preload=jobs > 1)
        children.append(c)
        sel.register(c.rfd, selectors.EVENT_READ, c)

    def feed(c: _Child) -> None:
        c.path = None
        if todo:
            c.send(todo.popleft())

    def lost(c: _Child, reason: str) -> dict:
        path = c.path
        sel.unregister(c.rfd)
        children.remove(c)
        code = c.close(kill=True)
        if reason == "died":
            reason = f"damaged HDF5 file: the HDF5 library failed reading it (exit {code})"
        row = empty_row(path, "damaged", "damaged", reason)
        try:
            st = os.stat(path)
            row["size_bytes"], row["mtime"] = st.st_size, st.st_mtime
        except OSError:
            pass
        if todo:
            start()
        return row

    try:
        for _ in range(jobs):
            start()
        if prime:
            yield None
        while children:
            if stop is not None and stop():
                return
            now = time.monotonic()
            timeout = 0.2
            for c in list(children):
                if c.path is not None and now - c.since > deadline_s:
                    yield lost(c, f"damaged HDF5 file: reading its structure does not finish "
                                  f"(gave up after {deadline_s:g} s)")
                elif not c.ready and now - c.since > _STARTUP_S:
                    raise RuntimeError(f"catalogue worker did not start within {_STARTUP_S:g} s")
            for key, _ in sel.select(timeout):
                c = key.data
                lines = c.lines()
                if lines is None:
                    if c.path is None and not c.ready:
                        raise RuntimeError("catalogue worker exited at start")
                    if c.path is not None:
                        yield lost(c, "died")
                    else:
                        sel.unregister(c.rfd)
                        children.remove(c)
                        c.close()
                    continue
                for line in lines:
                    msg = json.loads(line)
                    if msg == "ready":
                        c.ready = True
                    else:
                        yield msg
                    feed(c)  # the next file, if any
                if c.path is None and not todo and c in children:
                    sel.unregister(c.rfd)
                    children.remove(c)
                    c.close(kill=not c.ready)
    finally:
        for c in children:
            c.close(kill=True)
        sel.close()


if __name__ == "__main__":  # a fresh child (see _Child)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _serve(sys.stdin.fileno(), sys.stdout.fileno())
