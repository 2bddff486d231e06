"""velab.filters against scipy.signal on long records: the coupling's zero-phase Butterworth and the anti-alias
FIR decimation, on 20 s at 1 kHz and 60 s at 50 kHz.

Run as ``python benchmarks/filters.py [--repeats N]``. The two implementations are called in turn, so that both
see the same machine load (a short filter repeated over ~50 ms per measurement); printed: the median time of
each, the ratio velab / scipy, and whether the results are the same to the last bit. The kernels are loaded (or
compiled) once before timing. No assertions.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np
import scipy.signal as ss

from velab import filters as F

CASES = [("20 s x 1 kHz", 1000.0, 20.0), ("60 s x 50 kHz", 50000.0, 60.0)]
COUPLING_HZ = 62.0  # the coupling's low-pass at the reference rig (2 x the manoeuvre's band)


def timed(fn, x, inner=1):
    """The time of one call, averaged over ``inner`` calls (a short filter is timed over ~50 ms: one
    preemption of a loaded machine would be most of a single call)."""
    t0 = time.perf_counter()
    for _ in range(inner):
        y = fn(x)
    return (time.perf_counter() - t0) / inner, y


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    n_rep = ap.parse_args().repeats
    F.warm_up()
    rng = np.random.default_rng(0)
    print(f"# velab.filters vs scipy.signal, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}, "
          f"{n_rep} runs each, median (ms)")
    print(f"{'record':<16}{'filter':<34}{'scipy':>9}{'velab':>9}{'ratio':>8}  same bits")
    for name, fs, dur in CASES:
        x = np.cumsum(rng.standard_normal(int(fs * dur))) * 0.01 + 0.1 * rng.standard_normal(int(fs * dur))
        sos = ss.butter(4, COUPLING_HZ, fs=fs, output="sos")
        q = max(1, int(fs // 1000))
        pairs = [(f"sosfiltfilt, Butterworth 4 at {COUPLING_HZ:g} Hz",
                  lambda v: ss.sosfiltfilt(sos, v), lambda v: F.sosfiltfilt(F.butter_lowpass_sos(4, COUPLING_HZ, fs), v))]
        if q > 1:
            h = ss.firwin(20 * q + 1, 1.0 / q, window="hamming")
            pairs.append((f"FIR decimation by {q} ({h.size} taps)",
                          lambda v: ss.resample_poly(v, 1, q, window=h, padtype="line"),
                          lambda v: F.fir_decimate(v, F.firwin_lowpass(20 * q + 1, 1.0 / q), q)))
        for label, theirs, ours in pairs:
            ts, to = [], []
            inner = max(1, int(0.05 / max(timed(theirs, x)[0], 1e-6)))
            for _ in range(n_rep):
                t, y_s = timed(theirs, x, inner)
                ts.append(t)
                t, y_o = timed(ours, x, inner)
                to.append(t)
            a, b = statistics.median(ts), statistics.median(to)
            print(f"{name:<16}{label:<34}{1e3 * a:>9.1f}{1e3 * b:>9.1f}{b / a:>8.2f}  {np.array_equal(y_s, y_o)}")


if __name__ == "__main__":
    main()
