"""GUI responsiveness during a 10 kHz recording: how late does a 10 ms QTimer fire?

Runs the real window (offscreen unless QT_QPA_PLATFORM says otherwise) with the real
recorder engine on the in-process simulated rig (real-time clock, 10 kHz streaming ADC),
arms, triggers and records a run through the window's controls (live plot, device
panel, online fits, final fit and the fit panel), while a probe QTimer measures its
own lateness. An idle baseline (same window, no recording) is measured first in the
same process. Prints p50 / p99 / max lateness and the ratio to the baseline; exits 1
if p99 during the recording is 50 ms or more.

    python benchmarks/gui_latency.py [--duration 10] [--rate 10000] [--idle 3]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")


class Probe:
    def __init__(self, interval_ms: int = 10):
        from PySide6.QtCore import Qt, QTimer

        self.interval = interval_ms / 1000.0
        self.late: list[float] = []
        self.timer = QTimer()
        self.timer.setTimerType(Qt.PreciseTimer)
        self.timer.setInterval(interval_ms)
        self.timer.timeout.connect(self._tick)
        self._last = None

    def start(self):
        self.late.clear()
        self._last = time.perf_counter()
        self.timer.start()

    def stop(self):
        self.timer.stop()

    def _tick(self):
        now = time.perf_counter()
        self.late.append(max(0.0, now - self._last - self.interval))
        self._last = now


def stats(xs):
    import numpy as np

    a = np.asarray(xs) * 1e3
    return {"n": a.size, "p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)), "max": float(a.max())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=10.0, help="recorded after the trigger, s")
    ap.add_argument("--pretrigger", type=float, default=2.0)
    ap.add_argument("--rate", type=float, default=10000.0)
    ap.add_argument("--idle", type=float, default=3.0, help="idle baseline, s")
    ap.add_argument("--fit-window", type=float, default=5.0)
    args = ap.parse_args(argv)

    from velab.gui.app import ensure_app, recorder_factory
    from velab.gui.main_window import MainWindow, make_settings

    app = ensure_app()
    tmp = tempfile.mkdtemp(prefix="velab-gui-latency-")
    factory, rig = recorder_factory(simulate=True, clock="realtime")
    win = MainWindow(settings=make_settings(os.path.join(tmp, "gui.ini")), recorder_factory=factory, rig=rig)
    win.resize(1366, 740)
    rp = win.run_panel
    rp.duration_spin.setValue(args.duration)
    rp.pre_spin.setValue(args.pretrigger)
    rp.fit_window_spin.setValue(args.fit_window)
    rp.rate_combo.setCurrentIndex(rp.rate_combo.findData(args.rate))
    rp.out_edit.setText(os.path.join(tmp, "runs"))
    win.show()
    probe = Probe()

    def spin(seconds, until=None):
        t_end = time.perf_counter() + seconds
        while time.perf_counter() < t_end and not (until and until()):
            app.processEvents()
            time.sleep(0.001)

    spin(0.5)
    probe.start()
    spin(args.idle)
    probe.stop()
    idle = stats(probe.late)

    probe.start()
    t0 = time.perf_counter()
    win.arm()
    spin(60, lambda: win.controller.phase == "pretrigger")
    spin(60, lambda: win.live.samples_received >= args.pretrigger * args.rate)
    win.controller.trigger()
    spin(args.duration + 120, lambda: win.last_summary is not None)
    spin(10, lambda: win.fit_panel.data is not None)
    probe.stop()
    rec_s = time.perf_counter() - t0
    busy = stats(probe.late)
    s = win.last_summary
    print(f"velab gui latency: probe QTimer 10 ms, platform {app.platformName()}, Python {sys.version.split()[0]}")
    print(f"run: {s.status if s else 'none'}, {s.n_samples if s else 0} samples at {args.rate:g} Hz "
          f"({win.live.samples_received} shown live, {win.live.redraws} redraws), best model "
          f"{s.best_model if s else '-'}, {rec_s:.1f} s wall")
    for name, st in (("idle", idle), ("recording", busy)):
        print(f"{name:>10}: n={st['n']:5d}  p50 {st['p50']:6.2f} ms  p99 {st['p99']:6.2f} ms  max {st['max']:6.2f} ms")
    print(f"     ratio: p50 x{busy['p50'] / max(idle['p50'], 1e-3):.1f}, p99 x{busy['p99'] / max(idle['p99'], 1e-3):.1f} "
          f"(recording / idle)")
    ok = busy["p99"] < 50.0 and s is not None and s.status == "completed"
    print("PASS: p99 < 50 ms" if ok else "FAIL: p99 >= 50 ms or the run did not complete")
    win.close()
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
