"""Cyclic garbage collection on the GUI thread only, while a window is open.

A collection runs on whichever thread's allocation triggers it. Started on a worker thread (a GUI task,
the recorder's acquisition or fit threads), it can destroy Qt wrappers: their QObject::disconnect holds
Qt's connection mutex and asks for the GIL (PySide's disconnectNotify), while the GUI thread, holding
the GIL, waits for that mutex in its own disconnect (a plot cleared). Both wait for ever: seen in
tests/gui/test_gui_archive.py::test_open_refit_export, the figure export importing matplotlib on a pool
thread while the fit panel redrew. pyqtgraph's GarbageCollector is the known remedy: automatic
collection off, the generations collected from a QTimer on the GUI thread (1 s). Reference-counted by
window, so that the interpreter collects on its own again once no window is open.
"""

from __future__ import annotations

import gc

_holders = 0
_collector = None


def acquire() -> None:
    """A window opened (on the GUI thread)."""
    global _holders, _collector
    if _holders == 0:
        from pyqtgraph.util.garbage_collector import GarbageCollector

        _collector = GarbageCollector(interval=1.0)  # (gc.disable(), and a QTimer that collects)
    _holders += 1


def release() -> None:
    """A window closed (on the GUI thread): the last one gives collection back to the interpreter."""
    global _holders, _collector
    if _holders == 0:
        return
    _holders -= 1
    if _holders == 0 and _collector is not None:
        _collector.timer.stop()
        _collector = None
        gc.enable()
        gc.collect()


def active() -> bool:
    return _holders > 0
