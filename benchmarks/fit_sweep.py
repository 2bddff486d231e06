"""Time the whole EL..S6 sweep on the material A run (1 kHz, 20 s) against a plain baseline.

Baseline: scipy.optimize.least_squares (TRF) with a finite-difference Jacobian on the
full-band model (the impedance at every FFT bin), from the same kind of starting point
a user would write (nominal wave speed, log-spaced retardation times), same bounds.

    python benchmarks/fit_sweep.py            # synthesises the run in memory (seed 2018)
    python benchmarks/fit_sweep.py RUN.h5     # or uses a run file
"""

from __future__ import annotations

import sys
import time

import numpy as np
from scipy.optimize import least_squares

from velab.config import load_material, load_rig
from velab.fitting import fit_sweep
from velab.fitting.engine import HeadEvaluator, ParamMap
from velab.model import valve_head


def load(argv):
    if len(argv) > 1:
        from velab.runfile import read_run

        run = read_run(argv[1])
        t, h = run.fit_window(20.0)
        return t, h, run.rig
    rig = load_rig("perugia")
    t = np.arange(20000) / 1000.0
    h = valve_head(t, rig, load_material("A")) + np.random.default_rng(2018).normal(0, 0.1, t.size)
    return t, h, rig


def baseline(t, h, rig, m: int):
    ev = HeadEvaluator(rig, t, band_hz=None)
    pm = ParamMap(m)
    a0 = rig.nominal_wave_speed_m_s
    taus = np.geomspace(0.02, 10.0, m) if m > 1 else np.array([0.5] * m)
    E = np.full(m, 1e10)
    x0 = pm.clip(pm.pack(a0, E, E * taus))
    lo, hi = pm.bounds()

    def fun(x):
        return (ev.head(*pm.unpack(pm.project(x))) - h) / np.sqrt(h.size)

    r = least_squares(fun, x0, bounds=(lo, hi), method="trf", x_scale="jac", ftol=1e-12, xtol=1e-12,
                      gtol=1e-12, max_nfev=200 * (m + 1))
    return float(2 * r.cost), ev.evaluations


def main(argv):
    t, h, rig = load(argv)
    fit_sweep(t[:2000], h[:2000], rig, models="1", window_s=None)  # warm-up (FFT plans, imports)
    t0 = time.perf_counter()
    r = fit_sweep(t, h, rig, models=range(7), window_s=20.0)
    t_sweep = time.perf_counter() - t0
    print(f"velab sweep EL..S6: {t_sweep:.2f} s, {r.evaluations} model evaluations "
          f"({sum(f.jacobians for f in r.models)} with analytic Jacobian)")
    t0 = time.perf_counter()
    base = {}
    n_base = 0
    for m in range(7):
        F, nev = baseline(t, h, rig, m)
        base[m] = F
        n_base += nev
    t_base = time.perf_counter() - t0
    print(f"baseline (least_squares, finite differences, full band): {t_base:.2f} s, {n_base} model evaluations")
    print(f"speed-up: {t_base / t_sweep:.1f} x")
    ok = True
    print(f"{'model':<6}{'F sweep':>14}{'F baseline':>14}  sweep <= baseline")
    for f in r.models:
        good = f.F <= base[f.m] * (1 + 1e-9)
        ok &= good
        print(f"{f.name:<6}{f.F:>14.7e}{base[f.m]:>14.7e}  {'yes' if good else 'NO'}")
    print("sweep F equal or lower than the baseline for every model:", "yes" if ok else "NO")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv))
