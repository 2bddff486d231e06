"""GUI responsiveness during a 10 kHz recording with the online fit beside it: how late does a
10 ms QTimer fire on the GUI thread?

Runs the real window (offscreen unless QT_QPA_PLATFORM says otherwise) with the real recorder
engine on the in-process simulated rig (real-time clock, 10 kHz streaming ADC), presses Arm
and Trigger in the window's control bar as soon as each is enabled, and records a run (live
plot, device panel, intermediate online fits, the final fit) while a precise probe QTimer
measures its own lateness. The event loop runs as in the application (QEventLoop, no polling).
An idle baseline (same window, connected, no recording) is measured first in the same process.
Prints p50 / p99 / max lateness, the ratio to the baseline and the GUI thread's CPU time; exits
1 if p99 during the recording is 50 ms or more (issue 13), its longest stall 250 ms or more
(issue 16), or the run did not complete.

    python benchmarks/gui_latency.py [--duration 10] [--rate 10000] [--idle 3] [--fit-window 5]
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
        self.cpu0 = time.thread_time()
        self.timer.start()

    def stop(self):
        self.timer.stop()
        self.cpu = time.thread_time() - self.cpu0

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
    ap.add_argument("--models", default="0-6")
    args = ap.parse_args(argv)

    from velab.gui.app import ensure_app, recorder_factory
    from velab.gui.main_window import MainWindow, make_settings
    from velab.gui.eventloop import wait_until

    app = ensure_app()
    tmp = tempfile.mkdtemp(prefix="velab-gui-latency-")
    factory, rig = recorder_factory(simulate=True, clock="realtime")
    win = MainWindow(settings=make_settings(os.path.join(tmp, "gui.ini")), recorder_factory=factory, rig=rig)
    win.resize(1366, 768)
    rp, rc = win.run_panel, win.run_controls
    rp.duration_spin.setValue(args.duration)
    rp.pre_spin.setValue(args.pretrigger)
    rp.fit_window_spin.setValue(args.fit_window)
    rp.models_edit.setText(args.models)
    rp.rate_combo.setCurrentIndex(rp.rate_combo.findData(args.rate))
    rp.out_edit.setText(os.path.join(tmp, "runs"))
    win.show()
    probe = Probe()

    rc.connect_button.click()
    if not wait_until(lambda: rc.arm_button.isEnabled(), 120):
        print("FAIL: Arm never enabled", win.log.texts())
        return 1
    wait_until(lambda: False, 0.5)
    probe.start()
    wait_until(lambda: False, args.idle)
    probe.stop()
    idle, idle_cpu = stats(probe.late), probe.cpu

    probe.start()
    t0 = time.perf_counter()
    rc.arm_button.click()
    wait_until(lambda: rc.trigger_button.isEnabled(), 120)
    wait_until(lambda: win.live.samples_received >= args.pretrigger * args.rate, 60)  # the baseline, live
    rc.trigger_button.click()
    wait_until(lambda: win.last_summary is not None, args.duration + 180)
    wait_until(lambda: win.fit_panel.result is not None and "final fit" in win.fit_panel.title, 30)
    probe.stop()
    rec_s = time.perf_counter() - t0
    busy, busy_cpu = stats(probe.late), probe.cpu
    probe.start()  # the operator opens the Fit page: the final fit is drawn (in parts), its curves computed
    win.tabs.setCurrentWidget(win.fit_panel)
    wait_until(lambda: win.fit_panel.data is not None, 30)
    wait_until(lambda: False, 0.5)
    probe.stop()
    tab = stats(probe.late)
    s = win.last_summary
    print(f"velab gui latency: probe QTimer 10 ms, platform {app.platformName()}, Python {sys.version.split()[0]}")
    print(f"run: {s.status if s else 'none'}, {s.n_samples if s else 0} samples at {args.rate:g} Hz "
          f"({win.live.samples_received} shown live, {win.live.redraws} redraws), fit models {args.models}, "
          f"best {s.best_model if s else '-'}, {rec_s:.1f} s wall")
    for name, st, cpu, wall in (("idle", idle, idle_cpu, args.idle), ("recording", busy, busy_cpu, rec_s)):
        print(f"{name:>10}: n={st['n']:5d}  p50 {st['p50']:6.2f} ms  p99 {st['p99']:6.2f} ms  max {st['max']:6.2f} ms"
              f"  GUI-thread CPU {100 * cpu / wall:4.1f} %")
    print(f"     ratio: p50 x{busy['p50'] / max(idle['p50'], 1e-3):.1f}, p99 x{busy['p99'] / max(idle['p99'], 1e-3):.1f} "
          f"(recording / idle)")
    print(f"opening the Fit page after the run (the final fit drawn): longest stall {tab['max']:.0f} ms")
    ok = busy["p99"] < 50.0 and busy["max"] < 250.0 and s is not None and s.status == "completed"
    print("PASS: p99 < 50 ms, longest stall < 250 ms (issues 13, 16)" if ok
          else "FAIL: p99 >= 50 ms, a stall >= 250 ms, or the run did not complete")
    win.close()
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
