import os

# Qt tests run offscreen; set before any Qt import.
os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")


import pytest  # noqa: E402


@pytest.fixture()
def qt_cleanup(qtbot):
    """Delete a GUI test's windows while the QApplication lives (PySide6 crashes collecting
    them at interpreter exit); wait for the GUI's worker pool first."""
    yield
    import gc

    from PySide6.QtCore import QCoreApplication, QEvent

    from velab.gui import tasks

    tasks.wait_idle(20000)
    for _ in range(3):
        QCoreApplication.sendPostedEvents(None, QEvent.DeferredDelete)
        QCoreApplication.processEvents()
        gc.collect()
