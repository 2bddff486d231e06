"""Run the Qt event loop until a condition holds: for scripts that drive the window as an operator
(benchmarks/gui_latency.py, docs/make_screenshots.py). The loop runs as ``app.exec`` does, no
polling with processEvents, so what they measure or capture is what an operator sees."""

from __future__ import annotations

import time

from PySide6.QtCore import QEventLoop, QTimer


def wait_until(cond, timeout_s: float, interval_ms: int = 5) -> bool:
    """Run the event loop until ``cond()`` or ``timeout_s``; return ``cond()``."""
    loop = QEventLoop()
    deadline = time.perf_counter() + timeout_s
    check = QTimer()
    check.setInterval(interval_ms)
    check.timeout.connect(lambda: loop.quit() if cond() or time.perf_counter() > deadline else None)
    check.start()
    if not cond():
        loop.exec()
    check.stop()
    return bool(cond())
