"""velab.gui.gcguard: while a window is open, cyclic garbage is collected on the GUI thread only (a collection
on a worker thread that destroys Qt wrappers deadlocked the GUI thread: see the module's docstring)."""

from __future__ import annotations

import gc
import threading


def test_collections_move_to_the_gui_thread_while_a_window_is_open(qtbot, tmp_path):
    from velab.gui import gcguard
    from velab.gui.app import ensure_app
    from velab.gui.main_window import MainWindow, make_settings

    ensure_app()
    assert gc.isenabled() and not gcguard.active()
    win = MainWindow(settings=make_settings(tmp_path / "gui.ini"))
    qtbot.addWidget(win)
    assert gcguard.active() and not gc.isenabled()  # no thread's allocation starts a collection now

    # a worker thread makes cyclic garbage: nothing collects it there; the GUI thread's timer does
    class Cycle:
        pass

    collected_on = []
    gc.callbacks.append(lambda phase, info: collected_on.append(threading.current_thread().name)
                        if phase == "start" else None)
    try:
        def churn():
            for _ in range(20000):
                a, b = Cycle(), Cycle()
                a.b, b.a = b, a
        t = threading.Thread(target=churn, name="worker")
        t.start()
        t.join()
        assert "worker" not in collected_on
        qtbot.waitUntil(lambda: bool(collected_on), timeout=5000)  # the 1 s timer, on the GUI thread
        assert set(collected_on) == {threading.current_thread().name}
    finally:
        gc.callbacks.pop()
    win.close()
    assert gc.isenabled() and not gcguard.active()  # the interpreter collects on its own again
    win.close()  # (closed twice, released once)
    assert gc.isenabled() and not gcguard.active()
