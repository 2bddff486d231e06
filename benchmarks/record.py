"""Recording benchmark: long runs into HDF5 at 10 kHz (and 50 kHz headroom), fit latency.

    python benchmarks/record.py                  # 10 min at 10 kHz, 50 kHz headroom, fit latency
    python benchmarks/record.py --minutes 1 --scale 20 --skip-headroom

Everything runs in this process: the simulated rig (streaming ADC over a real socket,
Modbus valve and flowmeter), the recorder's threads and the HDF5 writer, on a
ScaledClock (``--scale`` x real time), so "CPU time per second of data" includes the
simulator's own CPU. Memory: RSS sampled during the run; flat means the last quarter
is not above the second quarter by more than a few MB.
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import threading
import time
from pathlib import Path


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize() / 1e6


def record(rate: float, seconds: float, scale: float, out: Path, fit: bool = False, window: float = 20.0):
    from velab.recorder import Recorder, RecordSettings

    s = RecordSettings(duration_s=seconds, pretrigger_s=2.0, sample_rate_hz=rate, out_dir=out, fit=fit,
                       fit_window_s=window, intermediate_fits=False)
    samples: list[tuple[float, float]] = []
    stop = threading.Event()

    def sampler():
        while not stop.wait(0.5):
            samples.append((time.monotonic(), rss_mb()))

    with Recorder.simulated(s, clock=f"scaled:{scale}") as rec:
        th = threading.Thread(target=sampler, daemon=True)
        cpu0, wall0 = time.process_time(), time.monotonic()
        th.start()
        summary = rec.run()
        cpu, wall = time.process_time() - cpu0, time.monotonic() - wall0
        stop.set()
        th.join()
    return summary, cpu, wall, samples


def report_long(name, rate, seconds, scale, out):
    summary, cpu, wall, mem = record(rate, seconds, scale, out)
    data_s = summary.n_samples / rate
    q = len(mem) // 4
    m2 = max(m for _, m in mem[q:2 * q]) if q else float("nan")
    m4 = max(m for _, m in mem[3 * q:]) if q else float("nan")
    print(f"{name}: {rate / 1e3:g} kHz x {seconds / 60:g} min (clock x{scale:g}): status {summary.status}, "
          f"{summary.n_samples} samples, lost {summary.lost_samples}, wall {wall:.1f} s, "
          f"CPU {cpu / data_s * 1e3:.1f} ms per s of data; RSS peak {max(m for _, m in mem):.0f} MB, "
          f"2nd quarter {m2:.0f} MB -> last quarter {m4:.0f} MB ({'flat' if m4 - m2 < 10 else 'GROWS'}); "
          f"file {summary.path.stat().st_size / 1e6:.0f} MB")
    return summary


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--scale", type=float, default=8.0, help="simulated clock speed-up for the 10 kHz run")
    ap.add_argument("--headroom-seconds", type=float, default=60.0)
    ap.add_argument("--skip-headroom", action="store_true")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    out = Path(args.out or tempfile.mkdtemp(prefix="velab-bench-record-"))
    report_long("main", 10_000.0, args.minutes * 60.0, args.scale, out)
    if not args.skip_headroom:
        report_long("headroom", 50_000.0, args.headroom_seconds, 1.0, out)
    lat = []
    for _ in range(3):
        summary, cpu, wall, _ = record(1000.0, 22.0, 1.0, out, fit=True)
        lat.append(summary.fit_latency_s)
        print(f"fit latency (1 kHz, 20 s window, EL..S6, real-time clock): {summary.fit_latency_s:.2f} s "
              f"after the window closed; best {summary.best_model}, a = {summary.wave_speed_m_s:.2f} m/s")
    print(f"fit latency max {max(lat):.2f} s (target < 5 s)")


if __name__ == "__main__":
    main()
