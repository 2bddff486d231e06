"""Fit time and peak memory against the record's sample rate (issue 13: a 10 kHz x 20 s record fits
in at most 1.5 x the 1 kHz time and under 400 MB; 50 kHz x 60 s fits in bounded memory).

Material A on the reference rig (linear friction, sigma = 0.1 m, seed 2018), synthesised at each
rate with 1 s before the trigger; each fit (velab.fitting.fit_record: the one fit path, with its
anti-alias decimation to the fit rate) runs in a fresh process, which reports its wall time and
its peak resident memory (ru_maxrss; the record itself included). The 1 kHz fit is the baseline
measured in the same run: the ratios of the others to it are printed.

    python benchmarks/fit_rate.py              # 1 kHz x 20 s, 10 kHz x 20 s, 50 kHz x 60 s (window 60 s)
    python benchmarks/fit_rate.py --quick      # 1 and 10 kHz only
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np

from velab.config import load_material, load_rig


def rig():
    return load_rig("perugia").with_changes(friction="linear")


def child(path: str, window_s: float) -> None:
    from velab.fitting import fit_record

    d = np.load(path)
    t, head, fs = d["t"], d["head"], float(d["fs"])
    t0 = time.perf_counter()
    r = fit_record(t, head, 0.0, rig(), window_s, record_rate_hz=fs)
    seconds = time.perf_counter() - t0
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(json.dumps({"seconds": seconds, "peak_mb": peak_mb, "best": r.best.name, "a": r.best.wave_speed_m_s,
                      "fit_rate_hz": r.sample_rate_hz, "n": r.n, "evaluations": r.evaluations}))


def make(folder: str, fs: float, seconds: float) -> str:
    from velab.model import valve_head

    rg = rig()
    t = np.arange(-int(fs), int(round(seconds * fs))) / fs
    head = rg.steady_head_m + valve_head(t, rg, load_material("A")) + np.random.default_rng(2018).normal(0, 0.1, t.size)
    path = os.path.join(folder, f"rec_{int(fs)}_{int(seconds)}.npz")
    np.savez(path, t=t, head=head, fs=fs)
    return path


def run_child(path: str, window_s: float) -> dict:
    out = subprocess.run([sys.executable, __file__, "--child", path, "--window", str(window_s)],
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="1 and 10 kHz only")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--window", type=float, default=20.0, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        child(args.child, args.window)
        return 0
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
          f"numpy {np.__version__}; load average {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    cases = [(1000.0, 20.0, 20.0), (10000.0, 20.0, 20.0)] + ([] if args.quick else [(50000.0, 60.0, 60.0)])
    res = {}
    ok = True
    with tempfile.TemporaryDirectory() as d:
        for fs, seconds, window in cases:
            res[fs] = run_child(make(d, fs, seconds), window)
    base = res[1000.0]
    print(f"{'record':<18}{'fit rate':>10}{'time (s)':>10}{'x 1 kHz':>9}{'peak (MB)':>11}{'x 1 kHz':>9}  best, a (m/s)")
    for (fs, seconds, window) in cases:
        r = res[fs]
        print(f"{fs / 1000:g} kHz x {seconds:g} s{'':<6}{r['fit_rate_hz']:>10.0f}{r['seconds']:>10.2f}"
              f"{r['seconds'] / base['seconds']:>9.2f}{r['peak_mb']:>11.0f}{r['peak_mb'] / base['peak_mb']:>9.2f}"
              f"  {r['best']}, {r['a']:.3f}")
    ten = res[10000.0]
    print(f"10 kHz / 1 kHz time: {ten['seconds'] / base['seconds']:.2f} (issue 13: <= 1.5); "
          f"10 kHz peak {ten['peak_mb']:.0f} MB (issue 13: < 400)")
    same = ten["best"] == base["best"] and abs(ten["a"] - base["a"]) < 0.3
    print(f"same best model and wave speed within 0.3 m/s at 1 and 10 kHz: {'yes' if same else 'NO'}")
    ok &= same
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
