"""Walk a file's HDF5 structure in a child process first, under a deadline.

Some damage makes the HDF5 library itself loop forever (found by the fuzz: a
zeroed range in an object header makes an attribute read never return), or
crash; h5py holds the GIL inside the library, so no thread or signal of ours can
stop it. Before velab reads a file in its own process it walks every group,
attribute and chunk index once in a child process (h5py only): a child that does
not answer within :func:`probe_timeout_s` (10 s; ``VELAB_PROBE_TIMEOUT_S`` sets another, for
archives on a slow network drive) is killed, a child that dies is
named by its exit status, and either is a one-line DataError; the file is then
never touched by the parent's HDF5.

The child is a small server kept for the next file (its start-up, the imports,
costs ~0.3 s: paid once per process, not once per file, so a batch of fifty runs
does not spend fifteen seconds starting interpreters). :func:`start_walker` starts it
without waiting for it, as soon as a command knows the files it will read (``velab fit``,
before it imports the fitter): its start-up then runs on another core while this
process goes on, and the first walk finds it ready. Nothing else changes: the walk's
deadline starts when its path is sent, the start-up's own when it is first waited for,
and a child started so that was never used is killed at exit, not waited for. A child that failed on a
file, timed out or died is not reused: the next file gets a fresh one, so a
damaged file can never leave a library state that another file's walk would see.
A process that forked after starting a child does not share it (the pipes are
the parent's): it starts its own.

Files this process wrote or saved itself, and files already walked, are not
walked again while their (device, inode, size, mtime) stay the same.
"""

from __future__ import annotations

import atexit
import json
import os
import select
import subprocess
import sys
import threading
import time
from pathlib import Path

from velab.errors import DataError

PROBE_TIMEOUT_S = 10.0  # the default deadline of one file's walk
STARTUP_S = 60.0  # a fresh child's imports, on a loaded machine
_known: set[tuple] = set()
_lock = threading.Lock()  # guards _known
_walk_lock = threading.Lock()  # one file at a time through the one child

# The child: one JSON path a line in, one JSON [exit code, last line said] a line out.
_SERVER = """
import contextlib, io, json, sys
from velab.runfiles.h5open import walk
out = sys.stdout
out.write("ready\\n")
out.flush()
for line in sys.stdin:
    said = io.StringIO()
    with contextlib.redirect_stdout(said):
        code = walk(json.loads(line))
    last = (said.getvalue().strip().splitlines() or [""])[-1]
    out.write(json.dumps([code, last]) + "\\n")
    out.flush()
"""


def probe_timeout_s() -> float:
    """The deadline of one file's walk: ``VELAB_PROBE_TIMEOUT_S`` seconds if set, else 10."""
    text = os.environ.get("VELAB_PROBE_TIMEOUT_S", "").strip()
    if not text:
        return PROBE_TIMEOUT_S
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0.0 < value < float("inf"):
        raise DataError(f"VELAB_PROBE_TIMEOUT_S: expected a number of seconds > 0, got {text!r}")
    return value


def _key(path: Path) -> tuple | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)


def trust(path: str | os.PathLike) -> None:
    """``path`` was just written or saved by this process: no need to walk it."""
    key = _key(Path(path))
    if key is not None:
        with _lock:
            _known.add(key)


class _Walker:
    """The child process that walks files, one at a time, each under the deadline."""

    def __init__(self):
        env = dict(os.environ, VELAB_PROBE_CHILD="1")
        self.owner = os.getpid()
        self.proc = subprocess.Popen([sys.executable, "-c", _SERVER], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.DEVNULL, env=env, close_fds=True)
        self._buf = b""
        self.ready = False  # the server said it has imported what it needs

    def walk(self, path: Path, timeout_s: float) -> tuple[int, str]:
        """(0, "") for a sound file, (3, the reader's line) for a damaged one; raises TimeoutError when the
        child does not answer in time, ChildProcessError (its exit status) when it dies. The deadline is the
        walk's: a fresh child's start-up (its imports, seconds on a loaded machine) has its own."""
        if not self.ready:
            if self._line(time.monotonic() + STARTUP_S) != b"ready":
                raise ChildProcessError(self.proc.wait())
            self.ready = True
        self.proc.stdin.write((json.dumps(str(path)) + "\n").encode())
        self.proc.stdin.flush()
        code, said = json.loads(self._line(time.monotonic() + timeout_s))
        return int(code), str(said)

    def _line(self, deadline: float) -> bytes:
        fd = self.proc.stdout.fileno()
        while b"\n" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError
            ready, _, _ = select.select([fd], [], [], left)
            if ready:
                chunk = os.read(fd, 65536)
                if not chunk:  # died: its exit status says how
                    raise ChildProcessError(self.proc.wait())
                self._buf += chunk
        line, self._buf = self._buf.split(b"\n", 1)
        return line

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()
        for f in (self.proc.stdin, self.proc.stdout):
            try:
                f.close()
            except OSError:
                pass


_walker: _Walker | None = None


def _ours() -> _Walker | None:
    """The walker of this process, or None (called with _walk_lock held)."""
    global _walker
    if _walker is not None and (_walker.owner != os.getpid() or _walker.proc.poll() is not None):
        _walker = None  # forked from the process that started it, or gone: not ours to use
    return _walker


def start_walker(paths=()) -> None:
    """Start the child that walks files now, without waiting for its start-up, when one of ``paths`` is a file
    that :func:`ensure_walkable` will walk (not one this process wrote or walked; never in the child itself). A
    command calls it as soon as it knows its files, so that the child's imports run beside its own. Nothing is
    raised: a child that cannot be started is tried again, and failed as before, at the first walk."""
    global _walker
    if os.environ.get("VELAB_PROBE_CHILD"):
        return
    keys = [_key(Path(p)) for p in paths]
    with _lock:
        if not any(k is not None and k not in _known for k in keys):
            return  # nothing to walk (missing files included: the read says what is wrong)
    if not _walk_lock.acquire(blocking=False):
        return  # a walk is under way: the child exists
    try:
        if _ours() is None:
            _walker = _Walker()
    except OSError:
        pass
    finally:
        _walk_lock.release()


def _walk(path: Path) -> tuple[int, str]:
    """Walk ``path`` in the child (started on first use, or by :func:`start_walker`; replaced after any
    failure)."""
    global _walker
    timeout_s = probe_timeout_s()
    with _walk_lock:
        if _ours() is None:
            _walker = _Walker()
        w = _walker
        try:
            code, said = w.walk(path, timeout_s)
        except TimeoutError:
            _walker = None
            w.close()
            if not w.ready:
                raise DataError(f"{path}: cannot check the file: the process that walks it did not start within "
                                f"{STARTUP_S:g} s") from None
            raise DataError(f"{path}: damaged HDF5 file: reading its structure does not finish "
                            f"(gave up after {timeout_s:g} s)") from None
        except (ChildProcessError, OSError) as exc:  # died on the file (or the pipe broke with it)
            _walker = None
            w.close()
            status = exc.args[0] if isinstance(exc, ChildProcessError) else w.proc.returncode
            raise DataError(f"{path}: damaged HDF5 file: the HDF5 library failed reading it (exit {status})") from None
        if code != 0:  # a damaged file: the next one gets a fresh child
            _walker = None
            w.close()
        return code, said


@atexit.register
def _close_walker() -> None:
    w = _walker
    if w is not None and w.owner == os.getpid():
        if not w.ready:  # started ahead (start_walker) and never used: its imports are not waited for
            w.close()
            return
        try:
            w.proc.stdin.close()  # the server ends at its input's end
            w.proc.wait(timeout=2.0)
        except (OSError, subprocess.TimeoutExpired):
            pass
        w.close()


def ensure_walkable(path: Path) -> None:
    key = _key(path)
    with _lock:
        if key is not None and key in _known:
            return
    if os.environ.get("VELAB_PROBE_CHILD"):  # we are the child: no grandchildren
        return
    try:
        code, said = _walk(path)
    except OSError:  # cannot start a child: read in-process (no deadline)
        return
    if code == 0:
        with _lock:
            if key is not None and key == _key(path):
                _known.add(key)
        return
    if code == 3 and said:
        raise DataError(said)
    raise DataError(f"{path}: damaged HDF5 file: the HDF5 library failed reading it (exit {code})")
