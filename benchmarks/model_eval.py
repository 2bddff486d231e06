"""Time one model evaluation: band-limited vs full-band frequency model vs MOC.

Run as ``python benchmarks/model_eval.py``. Reference case: Perugia rig,
material A (S3), 1 kHz sampling, records of 10, 20, 40 and 80 s from the trigger.

What is timed (best of several repeats, time.perf_counter):

* band    -- ``ValveHeadModel(rig, t, band_hz="auto")`` built once, ``head(A)`` timed:
             the cost of one objective evaluation in a calibration;
* full    -- the same with ``band_hz=None`` (every FFT bin), built once, ``head(A)`` timed;
* full+build -- ``valve_head(t, rig, A)``: construction (flow FFT) included;
* moc     -- ``moc_solve(rig, A, T, 1e-3)`` with linearised friction.

Also printed: the accuracy of each against the full-band reference at 20 s
(max and RMS difference, m), so that speed and error are read together.
No assertions: timings depend on the machine.
"""

from __future__ import annotations

import platform
import time

import numpy as np

from velab.config import load_material, load_rig
from velab.model import ValveHeadModel, valve_head
from velab.moc import moc_solve

DT_S = 1e-3
RECORDS_S = (10.0, 20.0, 40.0, 80.0)


def best_time(fn, budget_s: float = 1.0, min_repeats: int = 3, max_repeats: int = 200) -> float:
    """Minimum wall time of fn() over repeats; repeats until ~budget_s spent (at least min_repeats)."""
    times = []
    start = time.perf_counter()
    while len(times) < max_repeats:
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
        if len(times) >= min_repeats and time.perf_counter() - start > budget_s:
            break
    return min(times)


def fmt_ms(s: float) -> str:
    return f"{s * 1e3:10.2f}"


def main() -> None:
    rig = load_rig("perugia")
    mat = load_material("A")
    print(f"velab model evaluation benchmark -- rig {rig.name!r}, material {mat.name} ({mat.model_name}), "
          f"dt = {DT_S * 1e3:g} ms")
    print(f"python {platform.python_version()}, numpy {np.__version__}, {platform.machine()}")
    print()
    header = (f"{'record s':>8} {'samples':>8} {'bins band/full':>15} {'band ms':>10} {'full ms':>10} "
              f"{'full+build':>10} {'moc ms':>10} {'full/band':>9} {'moc/band':>9}")
    print(header)
    print("-" * len(header))
    rows = []
    for T in RECORDS_S:
        t = np.arange(int(round(T / DT_S)) + 1) * DT_S
        band = ValveHeadModel(rig, t, band_hz="auto")
        full = ValveHeadModel(rig, t, band_hz=None)
        tb = best_time(lambda: band.head(mat))
        tf = best_time(lambda: full.head(mat))
        tfb = best_time(lambda: valve_head(t, rig, mat))
        tm = best_time(lambda: moc_solve(rig, mat, T, DT_S), budget_s=2.0, min_repeats=2 if T < 40 else 1)
        rows.append((T, tb, tf, tm))
        print(f"{T:8.0f} {t.size:8d} {band.band.n_bins:7d}/{full.band.n_bins:<7d} {fmt_ms(tb)} {fmt_ms(tf)} "
              f"{fmt_ms(tfb)} {fmt_ms(tm)} {tf / tb:9.1f} {tm / tb:9.0f}")

    # growth with record length, relative to the 10 s record
    print()
    print("growth relative to the 10 s record (x record length):")
    T0, b0, f0, m0 = rows[0]
    for T, tb, tf, tm in rows:
        print(f"  {T:5.0f} s ({T / T0:3.0f}x): band {tb / b0:5.1f}x   full {tf / f0:5.1f}x   moc {tm / m0:5.1f}x")

    # accuracy at 20 s against the full-band reference
    T = 20.0
    t = np.arange(int(round(T / DT_S)) + 1) * DT_S
    ref = valve_head(t, rig, mat)
    hb = ValveHeadModel(rig, t, band_hz="auto").head(mat)
    r = moc_solve(rig, mat, T, DT_S)
    ref_moc_grid = valve_head(r.t_s, rig, mat)
    hj = rig.joukowsky_head_m(mat.wave_speed_m_s)
    print()
    print(f"accuracy at {T:g} s against the full-band model (Joukowsky head {hj:.3f} m):")
    d = hb - ref
    print(f"  band 'auto' : max {np.abs(d).max():.4f} m, RMS {np.sqrt(np.mean(d**2)):.4f} m")
    d = r.head_m - ref_moc_grid
    print(f"  MOC (linear): max {np.abs(d).max():.4f} m = {np.abs(d).max() / hj:.1e} hJ, "
          f"RMS {np.sqrt(np.mean(d**2)):.4f} m (dt' = {r.dt_s * 1e3:.5f} ms, N = {r.n_reaches})")


if __name__ == "__main__":
    main()
