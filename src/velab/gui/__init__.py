"""Operator GUI (PySide6 + pyqtgraph); imports Qt, so nothing outside velab.gui imports it.

Modules: ``main_window`` (the window), ``controller`` (recorder events -> Qt signals,
commands as futures, the engine's phase), ``state`` (Qt-free: buttons and phase line from
the engine's phase and allowed commands), ``run_page`` (+ ``run_controls``, ``run_panel``,
``devices``), ``live_plot`` (+ ``strip_chart``), ``fit_panel`` (+ ``fit_rows``), ``archive`` (the
Archive tab: ``catalogue_view`` + ``catalogue_table``, ``run_view``, ``fit_controller``; ``archive_io``, the
file work on worker threads), ``messages``, ``widgets``, ``tasks`` (the worker pool; fit-service Futures
to signals), ``app`` (start-up, recorder factory). See docs/gui.md.
"""

import sys as _sys


def _pin_singletons() -> None:
    """Make Python's static singletons effectively immortal on Python < 3.12.

    PySide6 6.11/6.12 wheels (abi3) release references to ``None``, ``True`` and a
    few other static singletons that they never took on Python 3.11 (on 3.12+ these
    objects are immortal, so it goes unnoticed there): a signal emission costs
    ``True`` one reference, painting costs ``None`` some. After a few thousand
    signals the interpreter aborts ("deallocating None/True"). These objects are
    statically allocated and never freed, so adding a large number of references
    to them is harmless and does what 3.12 does. See docs/gui.md.
    """
    if _sys.version_info >= (3, 12) or _sys.implementation.name != "cpython" or hasattr(_sys, "gettotalrefcount"):
        return
    import ctypes

    objs = [None, True, False, ..., NotImplemented, (), "", b""] + list(range(-5, 257))
    for o in objs:
        ref = ctypes.c_ssize_t.from_address(id(o))
        if ref.value < (1 << 40):
            ref.value += 1 << 40


_pin_singletons()
