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
    from velab.recording import Recorder, RecordSettings

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


def writer_baseline(rate: float, seconds: float, out: Path) -> float:
    """CPU per second of data of the bare run-file writer: the same fast channels, appended in
    0.1 s blocks and flushed every 0.25 s, with no devices, threads or simulator."""
    import numpy as np

    from velab.config import load_rig
    from velab.runfiles import HEAD, Channel, RunWriter

    chans = (HEAD, Channel("pressure", "Pa"), Channel("pressure_raw", "counts", "i4"),
             Channel("valve_position", "%"), Channel("valve_position_raw", "counts", "i4"),
             Channel("sample_index", "samples", "i8"), Channel("host_time", "s"))
    block = int(rate / 10)
    rng = np.random.default_rng(0)
    x = rng.standard_normal(block)
    raw = (x * 1000).astype(np.int32)
    path = out / f"baseline_{int(rate)}.h5"
    cpu0 = time.process_time()
    w = RunWriter(path, load_rig("perugia"), sample_rate_hz=rate, channels=chans)
    n, last_flush = 0, 0
    while n < rate * seconds:
        idx = np.arange(n, n + block)
        w.append(idx / rate, head=x, pressure=x, pressure_raw=raw, valve_position=x, valve_position_raw=raw,
                 sample_index=idx, host_time=idx / rate)
        n += block
        if n - last_flush >= rate / 4:
            w.flush()
            last_flush = n
    w.close("completed")
    cpu = time.process_time() - cpu0
    path.unlink()
    return cpu / seconds


def report_long(name, rate, seconds, scale, out):
    rss0 = rss_mb()
    summary, cpu, wall, mem = record(rate, seconds, scale, out)
    data_s = summary.n_samples / rate
    base = writer_baseline(rate, min(seconds, 60.0), out)
    q = len(mem) // 4
    m2 = max(m for _, m in mem[q:2 * q]) if q else float("nan")
    m4 = max(m for _, m in mem[3 * q:]) if q else float("nan")
    print(f"{name}: {rate / 1e3:g} kHz x {seconds / 60:g} min (clock x{scale:g}): status {summary.status}, "
          f"{summary.n_samples} samples, lost {summary.lost_samples}, wall {wall:.1f} s, "
          f"CPU {cpu / data_s * 1e3:.1f} ms per s of data; RSS peak {max(m for _, m in mem):.0f} MB, "
          f"2nd quarter {m2:.0f} MB -> last quarter {m4:.0f} MB ({'flat' if m4 - m2 < 10 else 'GROWS'}); "
          f"file {summary.path.stat().st_size / 1e6:.0f} MB")
    print(f"  baseline (bare HDF5 writer, same channels): CPU {base * 1e3:.1f} ms per s of data -> the whole "
          f"recording costs {cpu / data_s / base:.1f}x storing alone; RSS before the run {rss0:.0f} MB, "
          f"peak {max(m for _, m in mem):.0f} MB ({max(m for _, m in mem) / rss0:.2f}x)")
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
    from velab.fitting import fit_sweep
    from velab.runfiles import read_run

    lat, offline = [], []
    for _ in range(3):
        summary, cpu, wall, _ = record(1000.0, 22.0, 1.0, out, fit=True)
        lat.append(summary.fit_latency_s)
        # baseline: the same sweep run offline on the recorded window, nothing else running
        run = read_run(summary.path)
        t, h = run.fit_window(20.0)
        t0 = time.perf_counter()
        fit_sweep(t, h, run.rig, models=range(7), window_s=None)
        offline.append(time.perf_counter() - t0)
        print(f"fit latency (1 kHz, 20 s window, EL..S6, real-time clock): {summary.fit_latency_s:.2f} s "
              f"after the window closed; best {summary.best_model}, a = {summary.wave_speed_m_s:.2f} m/s; "
              f"offline sweep on the same window {offline[-1]:.2f} s (ratio {summary.fit_latency_s / offline[-1]:.2f})")
    print(f"fit latency max {max(lat):.2f} s (target < 5 s); median ratio to the offline sweep "
          f"{sorted(a / b for a, b in zip(lat, offline))[1]:.2f}")


if __name__ == "__main__":
    main()
