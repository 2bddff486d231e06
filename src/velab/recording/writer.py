"""The writer stage: the only thread that touches the run file (``velab.runfiles.writer.RunWriter``, SWMR).

Operations arrive on a queue (``put(op)``), each a small immutable message of velab.recording.ops
(Append, Event, Gap, Trigger, Value, Slow; Close last), applied through one table. It flushes every ``flush_interval_s`` (or 0.5 s
of data) and checks the room the file can still grow by before each flush: below a reserve of
4 MiB + 2 s of samples it ends the run (``failed``, "storage failure: disk full ...") while
the file can still be closed properly. A write that fails anyway (h5py: OSError or
RuntimeError) ends the run the same way.
"""

from __future__ import annotations

import logging
import os
import queue
import shutil
import sys
import threading
import time

from velab.recording.ops import Append, Close, Event, Gap, Slow, Trigger, Value

try:
    import resource
except ImportError:  # not POSIX: no file-size limit to read
    resource = None

log = logging.getLogger(__name__)
BYTES_PER_SAMPLE = 62  # all fast channels of the run file, per sample, with chunk slack
TRANSDUCER_BYTES_PER_SAMPLE = 25  # each further transducer's head, pressure, raw counts and quality


def bytes_per_sample(transducers: int = 1) -> int:
    """The run file's bytes per sample with ``transducers`` pressure transducers recorded."""
    return BYTES_PER_SAMPLE + TRANSDUCER_BYTES_PER_SAMPLE * max(0, transducers - 1)


def storage_room(path) -> int | None:
    """Bytes the file at ``path`` can still grow by: free disk space and the process's RLIMIT_FSIZE."""
    try:
        room = shutil.disk_usage(os.path.dirname(os.path.abspath(path))).free
        soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0] if resource else None
        if soft is not None and soft != resource.RLIM_INFINITY:
            try:
                room = min(room, soft - os.path.getsize(path))
            except (OSError, ValueError):
                pass
        return int(room)
    except OSError:
        return None


def _append(w, op: Append) -> int:
    w.append(op.t, **op.channels)
    return op.t.size


class WriterStage:
    def __init__(self, writer, fs: float, flush_interval_s: float, hooks, bytes_per_sample: int = BYTES_PER_SAMPLE):
        self.w = writer
        self.bytes_per_sample = bytes_per_sample
        self.path = writer.path
        self.fs = fs
        self.interval = flush_interval_s
        self.hooks = hooks
        self.q: queue.Queue = queue.Queue()
        self.error = ""  # the storage failure, if any
        self.closed = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="velab-recorder-writer", daemon=True)
        self._thread.start()

    def put(self, op) -> None:
        if not self.closed.is_set():
            self.q.put(op)

    def close(self, status: str, reason: str, timeout: float = 30.0) -> bool:
        self.q.put(Close(status, reason))
        self._thread.join(timeout)
        return not self._thread.is_alive()

    def reserve(self) -> int:
        """Room kept free for the rest of a flush interval and closing the file (HDF5 allocates in chunks)."""
        return (4 << 20) + 4 * int(0.5 * self.fs * self.bytes_per_sample)

    # each operation on the RunWriter ``w``; an append returns the samples it wrote (for the flush rule)
    _APPLY = {
        Append: lambda w, op: _append(w, op),
        Event: lambda w, op: w.event(op.t, op.kind, op.text),
        Gap: lambda w, op: w.gap(op.sample, op.lost),
        Trigger: lambda w, op: w.set_trigger_time(op.t),
        Value: lambda w, op: w.set_value(op.path, op.value),
        Slow: lambda w, op: w.append_slow(op.name, op.t, op.value, epoch_s=op.epoch_s),
    }

    def _apply(self, op) -> int:
        return self._APPLY[type(op)](self.w, op) or 0

    def _loop(self) -> None:
        last, pending, low, op = time.monotonic(), 0, False, None
        try:
            while True:
                try:
                    op = self.q.get(timeout=self.interval / 2)
                except queue.Empty:
                    op = None
                if isinstance(op, Close):
                    self.w.flush()
                    self.w.close(op.status, op.reason or self.error)
                    return
                if op is not None:
                    pending += self._apply(op)
                now = time.monotonic()
                if not low and (now - last >= self.interval or pending >= 0.5 * self.fs):
                    room = storage_room(self.path)
                    if room is not None and room < self.reserve():
                        low = True  # keep writing into the reserve until the engine closes the run
                        what = (f"disk full ({max(room, 0) / 1e6:.1f} MB left for the run file, "
                                f"{self.reserve() / 1e6:.1f} MB kept to close it): recording stopped")
                        self.error = f"storage failure: {what}"
                        self.hooks.fault("storage", what, "storage", path=str(self.path), room_bytes=int(room))
                        self.hooks.request_end("failed", self.error)
                    self.w.flush()
                    last, pending = now, 0
        except Exception as exc:  # noqa: BLE001 - disk full, I/O error (h5py: OSError or RuntimeError)
            self._failed(exc, closing=isinstance(op, Close))
        finally:
            self.closed.set()

    def _failed(self, exc: BaseException, closing: bool) -> None:
        what = f"write failed (disk full?): {str(exc).splitlines()[0][:160] if str(exc) else type(exc).__name__}"
        self.error = f"storage failure: {what}"
        quiet_h5py_dealloc_errors()
        self.hooks.fault("storage", what, "storage", path=str(self.path))
        self.hooks.request_end("failed", self.error)
        if closing:
            try:
                self.w._fh.close()
            except Exception:  # noqa: BLE001
                pass
            return
        while True:  # drain until the close request, then close as well as possible
            op = self.q.get()
            if isinstance(op, Close):
                try:
                    self.w.close(op.status, op.reason or self.error)
                except Exception:  # noqa: BLE001
                    try:
                        self.w._fh.close()
                    except Exception:  # noqa: BLE001
                        pass
                return


_hooks_installed = False


def quiet_h5py_dealloc_errors() -> None:
    """After a storage failure h5py reports every handle of the unwritable file it cannot release
    (a traceback on stderr per object, from its destructors): the failure is reported once, as the run's
    status; these are dropped. Only exceptions raised inside h5py's own code are filtered."""
    global _hooks_installed
    if _hooks_installed:
        return
    _hooks_installed = True
    prev_unraisable, prev_except = sys.unraisablehook, sys.excepthook

    def from_h5py(tb, where="") -> bool:
        if "h5py" in where:
            return True
        while tb is not None:
            if "h5py" in tb.tb_frame.f_code.co_filename and tb.tb_next is None:
                return True
            tb = tb.tb_next
        return False

    def unraisable(u):
        if isinstance(u.exc_value, (RuntimeError, OSError)) and from_h5py(u.exc_traceback,
                                                                        str(u.object or "") + str(u.err_msg or "")):
            return
        prev_unraisable(u)

    def excepthook(tp, value, tb):
        if isinstance(value, (RuntimeError, OSError)) and from_h5py(tb) and (
                "write failed" in str(value) or "ref count" in str(value) or "Unable to close" in str(value)):
            return
        prev_except(tp, value, tb)

    sys.unraisablehook = unraisable
    sys.excepthook = excepthook
