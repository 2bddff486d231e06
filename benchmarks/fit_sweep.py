"""Time the whole EL..S6 sweep on the material A run (1 kHz, 20 s) against a plain baseline,
and the same sweep on data with quadratic friction against the linear one.

Baseline: scipy.optimize.least_squares (TRF) with a finite-difference Jacobian on the
full-band model (the impedance at every FFT bin), from the same kind of starting point
a user would write (nominal wave speed, log-spaced retardation times), same bounds.

Quadratic friction: material A on the reference rig made by the time-domain model
(velab.moc.moc_head, quadratic friction, same noise), fitted with the rig's quadratic law
(the sweep's time-domain friction correction); the ratio to the linear sweep's median is
printed (issue 10: at most 3).

    python benchmarks/fit_sweep.py                # synthesises the run in memory (seed 2018)
    python benchmarks/fit_sweep.py RUN.h5         # or a run file, prepared as the fit path does (decimated to the fit rate)
    python benchmarks/fit_sweep.py --repeat 5     # sweep timings to take the median of (default 3)
    python benchmarks/fit_sweep.py --no-baseline  # sweep only (the baseline takes minutes)
    python benchmarks/fit_sweep.py --no-quadratic # skip the quadratic-friction sweep

The previous sweep (before issue 13: every coarse start run to the full budget, tau-grid starts
solved with 25 evaluations, no stall test on the ridge crawl and the polish, tau-grid starts for
every model, every model searched, every better start handed back however small the gain, full-band
evaluations and coarse starts in one thread; and before the fifth round: EL solved by Gauss-Newton,
the equivalent linear friction matched on the full band, the hand-back also tried from models that
are a smaller one plus a vanished element) is timed in the
same run, interleaved with the current one, and its speed-up over the baseline printed beside
the current one (issue 13: at least twice the previous speed-up; --no-previous skips it).

Prints the sweep time (median of the repeats, and each repeat), the baseline time, the
speed-up, the model evaluations of both, and F per model for both. Exit code 1 if the
sweep's F is above the baseline's (relative 1e-9) for any model, or if the repeated
sweeps do not give identical results. Timings depend on the load: check `uptime` first.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import platform
import statistics
import sys
import time

import numpy as np
from scipy.optimize import least_squares

from velab.config import load_material, load_rig
from velab.fitting import fit_sweep, nesting as fit_nesting, solvers as fit_solvers, starts as fit_starts
from velab.fitting import sweep as fit_sweep_module
from velab.fitting.engine import HeadEvaluator
from velab.fitting.params import ParamMap, derive_bounds
from velab.model import creep_scale, valve_head
from velab.moc import moc_head


def load(path):
    if path:
        from velab.fitting import prepare_record
        from velab.runfiles import read_run

        run = read_run(path)
        # the fit path's preparation (steady head, window, decimation to the fit rate): what is fitted
        rec = prepare_record(run.time_s, run.head_m, run.trigger_time_s, run.rig, 20.0,
                             record_rate_hz=run.sample_rate_hz)
        return rec.t, rec.h, run.rig
    rig = load_rig("perugia").with_changes(friction="linear")
    t = np.arange(20000) / 1000.0
    h = valve_head(t, rig, load_material("A")) + np.random.default_rng(2018).normal(0, 0.1, t.size)
    return t, h, rig


def quadratic_record():
    """Material A on the reference rig from the time-domain model with quadratic friction."""
    rig = load_rig("perugia").with_changes(friction="quadratic")
    t = np.arange(20000) / 1000.0
    A = load_material("A")
    J = np.array([e.J_per_pa for e in A.elements]) * creep_scale(rig, A.wave_speed_m_s)
    tau = np.array([e.tau_s for e in A.elements])
    h = moc_head(rig, A.wave_speed_m_s, J, tau, t) + np.random.default_rng(2018).normal(0, 0.1, t.size)
    return t, h, rig


def baseline(t, h, rig, m: int):
    ev = HeadEvaluator(rig, t, band_hz=None)
    pm = ParamMap(m, derive_bounds(rig, float(t[1] - t[0]), t.size * float(t[1] - t[0])))
    a0 = rig.nominal_wave_speed_m_s
    taus = np.geomspace(0.02, 10.0, m) if m > 1 else np.array([0.5] * m)
    x0 = pm.clip(pm.pack(a0, np.full(m, 0.18), taus))  # J' = 0.18: E = 1e10 Pa on the reference rig
    lo, hi = pm.bounds()

    def fun(x):
        return (ev.head(*pm.unpack(pm.project(x))) - h) / np.sqrt(h.size)

    r = least_squares(fun, x0, bounds=(lo, hi), method="trf", x_scale="jac", ftol=1e-12, xtol=1e-12,
                      gtol=1e-12, max_nfev=200 * (m + 1))
    return float(2 * r.cost), ev.evaluations


@contextlib.contextmanager
def previous_sweep():
    """The sweep as it was before issue 13 (same code, the new limits switched off)."""
    sw = fit_sweep_module
    switches = [(fit_starts, "RACE_KEEP", 10**6), (fit_starts, "REDUCED_NFEV", 25), (sw, "STALL_GAIN", -1.0),
                (sw, "SATURATION", False), (sw, "SPLIT_FULL_BAND", False), (sw, "PARALLEL_STARTS", False),
                (sw, "NOTHING_LEFT", False), (fit_nesting, "MIN_GAIN", 0.0), (fit_nesting, "SKIP_EMBEDDED", False),
                (fit_solvers, "SECANT_1D", False), (sw, "COARSE_EQUIVALENT", False)]
    saved = [getattr(mod, name) for mod, name, _ in switches]
    for mod, name, value in switches:
        setattr(mod, name, value)
    try:
        yield
    finally:
        for (mod, name, _), value in zip(switches, saved):
            setattr(mod, name, value)


def _signature(r):
    return tuple((f.name, f.F, f.wave_speed_m_s, f.E_pa, f.eta_pa_s, f.evaluations) for f in r.models)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", nargs="?", help="run file (default: synthesise material A, seed 2018)")
    ap.add_argument("--repeat", type=int, default=3, help="sweep timings (median reported; default 3)")
    ap.add_argument("--no-baseline", action="store_true", help="skip the baseline (about 3 minutes)")
    ap.add_argument("--threads", type=int, default=None, help="fit_sweep(threads=...) (default: auto)")
    ap.add_argument("--no-quadratic", action="store_true", help="skip the quadratic-friction sweep")
    ap.add_argument("--no-previous", action="store_true", help="skip the previous sweep (before issue 13)")
    args = ap.parse_args(argv)

    t, h, rig = load(args.run)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
          f"numpy {np.__version__}; load average {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    print(f"record: n = {h.size} samples, window 20 s, models EL..S6")
    fit_sweep(t[:2000], h[:2000], rig, models="1", window_s=None)  # warm-up (FFT plans, imports)

    times, sigs, ptimes = [], set(), []
    r = rp = None
    for _ in range(max(1, args.repeat)):  # interleaved with the previous sweep: both see the same load
        t0 = time.perf_counter()
        r = fit_sweep(t, h, rig, models=range(7), window_s=20.0, threads=args.threads)
        times.append(time.perf_counter() - t0)
        sigs.add(_signature(r))
        if not args.no_previous:
            with previous_sweep():
                t0 = time.perf_counter()
                rp = fit_sweep(t, h, rig, models=range(7), window_s=20.0, threads=args.threads)
                ptimes.append(time.perf_counter() - t0)
    t_sweep = statistics.median(times)
    t_prev = statistics.median(ptimes) if ptimes else None
    n_jac = sum(f.jacobians for f in r.models)
    print()
    print(f"velab sweep EL..S6:  {t_sweep:7.2f} s  median of {len(times)} "
          f"({', '.join(f'{v:.2f}' for v in times)} s)")
    print(f"  model evaluations: {r.evaluations} ({n_jac} with the analytic Jacobian)")
    print(f"  repeated sweeps identical: {'yes' if len(sigs) == 1 else 'NO'}")
    ok = len(sigs) == 1
    if rp is not None:
        print(f"previous sweep (before issue 13): {t_prev:7.2f} s  median of {len(ptimes)} "
              f"({', '.join(f'{v:.2f}' for v in ptimes)} s), {rp.evaluations} model evaluations")
        print(f"  current / previous: {t_sweep / t_prev:.2f} (speed-up over the previous sweep {t_prev / t_sweep:.2f} x; "
              f"issue 13: >= 2)")
        worse = [f"{f.name} ({f.F / g.F - 1:+.1e})" for f, g in zip(r.models, rp.models) if f.F > g.F * (1 + 1e-9)]
        print(f"  F no worse than the previous sweep for every model: {'yes' if not worse else 'NO: ' + ', '.join(worse)}")
        print(f"  best model {r.best.name} (previous {rp.best.name}), a = {r.best.wave_speed_m_s:.3f} m/s "
              f"(previous {rp.best.wave_speed_m_s:.3f})")
        ok &= not worse

    if not args.no_quadratic:
        tq, hq, rq = quadratic_record()
        fit_sweep(tq[:2000], hq[:2000], rq, models="1", window_s=None)  # warm-up (MOC kernel)
        qtimes = []
        for _ in range(max(1, args.repeat)):
            t0 = time.perf_counter()
            rqr = fit_sweep(tq, hq, rq, models=range(7), window_s=20.0, threads=args.threads)
            qtimes.append(time.perf_counter() - t0)
        t_q = statistics.median(qtimes)
        fr = rqr.settings["friction"]
        print(f"quadratic friction sweep EL..S6: {t_q:7.2f} s  median of {len(qtimes)} "
              f"({', '.join(f'{v:.2f}' for v in qtimes)} s); {fr['moc_runs']} MOC runs, {fr['moc_seconds']:.2f} s")
        print(f"  ratio to the linear sweep: {t_q / t_sweep:.2f} (issue 10: <= 3)")
        print(f"  best {rqr.best.name}, a = {rqr.best.wave_speed_m_s:.2f} +- {rqr.best.wave_speed_se_m_s:.2f} m/s, "
              f"F/(N sigma^2) = {rqr.best.F / 0.01:.3f}; dAIC " +
              ", ".join(f"{f.name} {f.delta_aic:.1f}" for f in rqr.models))

    base = {}
    if not args.no_baseline:
        t0 = time.perf_counter()
        n_base = 0
        for m in range(7):
            F, nev = baseline(t, h, rig, m)
            base[m] = F
            n_base += nev
        t_base = time.perf_counter() - t0
        print(f"baseline (least_squares, finite differences, full band): {t_base:7.2f} s (one run)")
        print(f"  model evaluations: {n_base}")
        print(f"speed-up: {t_base / t_sweep:.1f} x" + (f" (previous sweep: {t_base / t_prev:.1f} x)" if t_prev else ""))

    print()
    if base:
        print(f"{'model':<6}{'evals':>7}{'F sweep':>16}{'F baseline':>16}{'(F_s-F_b)/F_b':>15}  sweep <= baseline")
    else:
        print(f"{'model':<6}{'evals':>7}{'F sweep':>16}{'delta AIC':>11}")
    for f in r.models:
        if base:
            good = f.F <= base[f.m] * (1 + 1e-9)
            ok &= good
            print(f"{f.name:<6}{f.evaluations:>7}{f.F:>16.9e}{base[f.m]:>16.9e}{f.F / base[f.m] - 1:>15.2e}  "
                  f"{'yes' if good else 'NO'}")
        else:
            print(f"{f.name:<6}{f.evaluations:>7}{f.F:>16.9e}{f.delta_aic:>11.3f}")
    if base:
        print("sweep F equal or lower than the baseline for every model:",
              "yes" if all(f.F <= base[f.m] * (1 + 1e-9) for f in r.models) else "NO")
    print(f"best model: {r.best.name}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
