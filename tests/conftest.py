import atexit
import os
import shutil
import sys
import tempfile

# Qt tests run offscreen; set before any Qt import.
os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

# The suite starts some hundreds of child interpreters (velab commands, simulators, fit workers):
# with PYTHONDONTWRITEBYTECODE set (some shells and CI images set it), each compiled velab's
# source again, 0.4-0.6 s a child on a 2-core box. Bytecode goes to __pycache__ as usual.
os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
sys.dont_write_bytecode = False

# Config lookup is hermetic: a developer's ~/.config/velab or $VELAB_CONFIG_PATH must not change
# what "perugia" or "A" means in a test (subprocesses inherit this too).
os.environ.pop("VELAB_CONFIG_PATH", None)
os.environ["XDG_CONFIG_HOME"] = tempfile.mkdtemp(prefix="velab-test-xdg-")
atexit.register(shutil.rmtree, os.environ["XDG_CONFIG_HOME"], True)

# Property-based tests: reproducible in CI (derandomised, no per-example deadline on a loaded
# 2-core machine); VELAB_FUZZ_EXAMPLES scales the number of examples for a longer local run.
try:
    from hypothesis import HealthCheck, settings

    settings.register_profile(
        "velab", derandomize=True, deadline=None, print_blob=True,
        max_examples=int(os.environ.get("VELAB_FUZZ_EXAMPLES", "150")),
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
    )
    settings.load_profile("velab")
except ImportError:  # hypothesis is a test extra; only the fuzz tests need it
    pass


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
    gc.unfreeze()  # a window froze the heap (velab.gui.app.freeze_heap): the closed windows must be collectable
    for _ in range(3):
        QCoreApplication.sendPostedEvents(None, QEvent.DeferredDelete)
        QCoreApplication.processEvents()
        gc.collect()
