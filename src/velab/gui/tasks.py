"""Background work for the GUI: run a function on a worker thread, get the result as a signal.

The GUI thread never reads or writes run files, fits or talks to devices; it hands
the work to :func:`submit`, which runs it on the GUI's own QThreadPool and delivers
``done(result)``, ``failed(exc)`` and ``progress(done, total, text)`` back on the GUI
thread (queued signals). A task keeps itself alive until it has reported.

:func:`watch` delivers a fit the same way: the Future of a fit submitted to the fit service
(velab.fitservice) and its FitProgress messages reach the GUI thread through the same signals.
"""

from __future__ import annotations

import traceback
from typing import Callable

import shiboken6
from PySide6.QtCore import QObject, QRunnable, QThreadPool, Signal, Slot

_POOL: QThreadPool | None = None
_LIVE: set["Task"] = set()


def pool() -> QThreadPool:
    global _POOL
    if _POOL is None:
        _POOL = QThreadPool()
        _POOL.setMaxThreadCount(2)
    return _POOL


class TaskSignals(QObject):
    done = Signal(object)
    failed = Signal(object)  # the exception; its traceback text is in exc.__velab_traceback__
    progress = Signal(int, int, str)
    finished = Signal()


class _Relay(QObject):
    """Lives on the GUI thread: the worker's signals are queued to it, it calls the callbacks
    (not when the widget that asked for the work, ``owner``, has been deleted meanwhile)."""

    def __init__(self, task: "Task", on_done, on_error, on_progress, owner=None):
        super().__init__()
        self.task, self.on_done, self.on_error, self.on_progress = task, on_done, on_error, on_progress
        self.owner = owner

    def _live(self) -> bool:
        return self.owner is None or shiboken6.isValid(self.owner)

    @Slot(object)
    def done(self, result) -> None:
        if self.on_done is not None and self._live():
            self.on_done(result)

    @Slot(object)
    def failed(self, exc) -> None:
        if self.on_error is not None and self._live():
            self.on_error(exc)

    @Slot(int, int, str)
    def progress(self, d: int, t: int, s: str) -> None:
        if self.on_progress is not None and self._live():
            self.on_progress(d, t, s)

    @Slot()
    def finished(self) -> None:
        _LIVE.discard(self.task)


class Task(QRunnable):
    """``fn(*args, progress=callback, **kwargs)`` if ``with_progress`` else ``fn(*args, **kwargs)``."""

    def __init__(self, fn: Callable, *args, with_progress: bool = False, **kwargs):
        super().__init__()
        self.setAutoDelete(False)
        self.fn, self.args, self.kwargs = fn, args, kwargs
        self.with_progress = with_progress
        self.signals = TaskSignals()

    def run(self) -> None:  # worker thread
        try:
            kw = dict(self.kwargs)
            if self.with_progress:
                kw["progress"] = lambda d, t, s="": self.signals.progress.emit(int(d), int(t), str(s))
            result = self.fn(*self.args, **kw)
        except BaseException as exc:  # reported, never raised into Qt
            try:
                exc.__velab_traceback__ = traceback.format_exc()
            except Exception:
                pass
            self.signals.failed.emit(exc)
        else:
            self.signals.done.emit(result)
        self.signals.finished.emit()


def submit(fn: Callable, *args, on_done=None, on_error=None, on_progress=None, owner=None, **kwargs) -> Task:
    """Run ``fn`` in the GUI's thread pool; callbacks run on the GUI thread, if ``owner`` (a QObject) lives."""
    task = Task(fn, *args, with_progress=on_progress is not None, **kwargs)
    relay = task.relay = _Relay(task, on_done, on_error, on_progress, owner)
    task.signals.done.connect(relay.done)
    task.signals.failed.connect(relay.failed)
    task.signals.progress.connect(relay.progress)
    task.signals.finished.connect(relay.finished)
    _LIVE.add(task)
    pool().start(task)
    return task


class _Watch:
    """A Future watched for the GUI thread (:func:`watch`): its relay and signals, kept alive until it reported."""

    def __init__(self):
        self.signals = TaskSignals()


def watch(future, *, on_done=None, on_error=None, owner=None):
    """``on_done(result)`` or ``on_error(exc)`` on the GUI thread when ``future`` (a concurrent Future, e.g.
    velab.fitservice's) ends, if ``owner`` lives; returns ``sink(FitProgress)``, the progress sink to give
    the fit service with the request (its messages reach ``on_progress`` of :func:`progress_sink`)."""
    w = _Watch()
    relay = w.relay = _Relay(w, on_done, on_error, None, owner)
    w.signals.done.connect(relay.done)
    w.signals.failed.connect(relay.failed)
    w.signals.finished.connect(relay.finished)
    _LIVE.add(w)

    def ended(f) -> None:  # the fit service's thread
        exc = f.exception()
        if exc is None:
            w.signals.done.emit(f.result())
        else:
            w.signals.failed.emit(exc)
        w.signals.finished.emit()
    future.add_done_callback(ended)
    return w


def progress_sink(on_progress, owner=None):
    """A FitProgress sink for the fit service whose messages call ``on_progress(done, total, name)`` on the
    GUI thread (if ``owner`` lives). Create it on the GUI thread."""
    w = _Watch()
    relay = w.relay = _Relay(w, None, None, on_progress, owner)
    w.signals.progress.connect(relay.progress)
    w.sink = lambda m: w.signals.progress.emit(int(m.done), int(m.total), str(m.name))
    return w


def wait_idle(ms: int = 30000) -> bool:
    """Wait for every queued task (closing the window, tests)."""
    return pool().waitForDone(ms)
