"""Calibration sweep EL, S1..S6 (and the reduced models) with a coarse-to-fine strategy.

Default method ``"auto"`` (see docs/fitting.md):

1. Coarse stage. The window is low-passed (ideal DCT filter) at the Nyquist
   frequency of a decimated grid that still holds the manoeuvre's band (about
   100 Hz sampling at the reference rig), and the band-limited model is evaluated on
   that grid: an evaluation costs 0.1-0.3 ms (full band: 1.5-4 ms). On it, every model is
   calibrated from several starts by a bounded Levenberg-Marquardt solver on the
   normal equations (``_Stage.lsq``) with the analytic Jacobian, in log variables:

   * EL: a scan of the wave speed over [0.5, 2] x nominal, then least squares;
   * Sm: retardation times log-spaced over the window's time scales (from a tenth
     of the closure time to half the window), several shifted grids, each first
     solved with tau fixed (the well-conditioned "reduced" problem) and then released;
   * nested starts from the best S(m-1): each element split in two, and one element
     added below, between and above the others (so F cannot get worse with m);
   * the previous result's parameters, if ``initial`` is given (warm start).

2. Fine stage ("polish"): the best distinct coarse solutions, plus the polished
   S(m-1) with one element split, are refined on the full-band model (every FFT bin)
   against every sample of the window, with the same solver (two candidates at once
   in two threads); a guard keeps F(Sm) <= F(S(m-1)).

Other methods replace the coarse local solver: ``"least-squares"`` (one start),
``"nelder-mead"`` (the paper's algorithm, on the coarse objective, from the same
starts) and ``"evolution"`` (scipy's differential evolution over the whole box). All
of them end with the same full-band polish unless ``polish=False``.
"""

from __future__ import annotations

import math
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable, Iterable

import numpy as np
import scipy.fft as sfft
from scipy.optimize import differential_evolution, minimize

from velab.config import REDUCED_RETARDATION_TIMES_S, Rig
from velab.errors import DataError
from velab.fitting.engine import HeadEvaluator, ParamMap, gram, sumsq
from velab.fitting.results import ModelFit, SweepResult, apply_criteria, lag1, model_name
from velab.model import manoeuvre_band_hz

METHODS = ("auto", "least-squares", "nelder-mead", "evolution")
MAX_M = 6
# Shortest retardation time calibrated, as a fraction of the valve's closure time: an
# element much faster than anything the manoeuvre excites cannot be told from the
# spring, and lets the optimiser trade a fast element against a higher wave speed.
TAU_MIN_FACTOR = 0.1


# --------------------------------------------------------------------------- data


def prepare_window(t_s, h_m, window_s: float | None):
    """Check and cut the record to the calibration window: samples with 0 <= t < window_s.

    Returns (t, h) starting at the trigger. Raises DataError (one line) for a bad record.
    """
    t = np.asarray(t_s, dtype=float)
    h = np.asarray(h_m, dtype=float)
    if t.ndim != 1 or h.shape != t.shape:
        raise DataError(f"time and head must be 1-D arrays of equal length (got {t.shape} and {h.shape})")
    if t.size < 16:
        raise DataError(f"record too short to calibrate ({t.size} samples)")
    dt = np.diff(t)
    step = float(np.median(dt))
    if not step > 0 or np.max(np.abs(dt - step)) > 1e-3 * step:
        raise DataError("time axis is not uniformly sampled")
    i0 = int(np.searchsorted(t, -0.5 * step))
    if i0 >= t.size:
        raise DataError("record has no samples after the trigger")
    if window_s is None:
        i1 = t.size
    else:
        if not window_s > 0:
            raise DataError(f"window must be positive, got {window_s:g} s")
        available = t[-1] - t[i0] + step
        if window_s > available * (1 + 1e-9) + 1e-9:
            raise DataError(f"window {window_s:g} s is longer than the record ({available:.6g} s after the trigger)")
        i1 = i0 + int(round(window_s / step))
        i1 = min(i1, t.size)
    tw, hw = t[i0:i1], h[i0:i1]
    bad = ~np.isfinite(hw)
    if bad.any():
        j = int(np.argmax(bad))
        raise DataError(f"head contains {int(bad.sum())} NaN/inf values in the window (first at t = {tw[j]:.6g} s)")
    if not np.all(np.isfinite(tw)):
        raise DataError("time axis contains NaN/inf values")
    return tw, hw


def lowpass_decimate(h: np.ndarray, q: int) -> np.ndarray:
    """Ideal low-pass at the Nyquist frequency of every q-th sample (DCT, even extension), decimated."""
    if q <= 1:
        return h.copy()
    c = sfft.dct(h, type=2, norm="ortho")
    n = h.size
    keep = int(math.ceil(n / q))
    c[keep:] = 0.0
    return sfft.idct(c, type=2, norm="ortho")[::q]


# --------------------------------------------------------------------------- problems


@dataclass
class _Sol:
    x: np.ndarray
    F: float
    pm: ParamMap


class _Stage:
    """One objective: an evaluator on a grid and the data on that grid."""

    def __init__(self, ev: HeadEvaluator, d: np.ndarray):
        self.ev = ev
        self.d = d
        self.sqn = math.sqrt(d.size)

    def F(self, pm: ParamMap, x) -> float:
        r = self.ev.head(*pm.unpack(x)) - self.d
        return sumsq(r) / self.d.size

    def residuals(self, pm: ParamMap, x) -> np.ndarray:
        return self.ev.head(*pm.unpack(x)) - self.d

    def lsq(self, pm: ParamMap, x0, *, max_nfev: int, ftol: float) -> _Sol:
        """Bounded Levenberg-Marquardt on F with the analytic Jacobian (normal equations).

        The Jacobian has n rows but only k <= 13 columns: working with the k x k
        matrix J^T J (column-scaled, Marquardt damping) costs far less than a
        factorisation of J itself. Bounds: variables at a bound whose gradient points
        outward are frozen; steps are projected on the box. Damping: Nielsen's update
        from the gain ratio (actual over predicted decrease), which avoids the
        accept/reject zig-zag of a fixed up/down factor along the J-tau ridge.

        The residual and the Jacobian are kept as 1 + k rows of length n (C order), so
        one Gram product [r; J] [r; J]^T gives J^T r and J^T J; the current and the
        trial point live in two buffers that are swapped on acceptance.
        """
        x = pm.clip(x0)
        n = self.d.size
        ev = self.ev
        tau_free = not pm.fixed_tau
        k = pm.size
        bufs = (np.empty((1 + k, ev.n_t)), np.empty((1 + k, ev.n_t)))
        cur = 0

        def evaluate(i, xe):
            b = bufs[i]
            ev.head_jac_x(*pm.unpack(xe), tau_free, out=b)
            b[0] -= self.d  # row 0: residual
            return sumsq(b[0]) / n

        F = evaluate(cur, x)
        lam = 1e-3
        nu = 2.0
        nfev = 1
        while nfev < max_nfev:
            M = gram(bufs[cur])
            g = M[1:, 0]
            A = M[1:, 1:]
            lo, hi = pm.bounds_at(x)
            free = ~(((x <= lo + 1e-12) & (g > 0)) | ((x >= hi - 1e-12) & (g < 0)))
            if not free.any():
                break
            if free.all():
                Af, gf = A, g
            else:
                Af = A[np.ix_(free, free)]
                gf = g[free]
            dscale = np.sqrt(np.maximum(np.diag(Af), 1e-300))
            As = Af / np.outer(dscale, dscale)
            gs = gf / dscale
            eye = np.eye(As.shape[0])
            improved = False
            while nfev < max_nfev:
                try:
                    step = -np.linalg.solve(As + lam * eye, gs) / dscale
                except np.linalg.LinAlgError:
                    lam *= 10
                    continue
                xt = x.copy()
                xt[free] += np.clip(step, -2.0, 2.0)
                xt = pm.project(xt)
                dx = xt - x
                if not np.any(dx):
                    break
                Ft = evaluate(1 - cur, xt)
                nfev += 1
                if Ft < F:
                    # predicted decrease of the linear model: -(|r + J dx|^2 - |r|^2)/n
                    pred = -(2 * np.dot(g, dx) + dx @ A @ dx) / n
                    rel = (F - Ft) / F
                    rho = min(max((F - Ft) / max(pred, 1e-300), 0.0), 2.0)
                    lam = max(lam * max(1 / 3, 1 - (2 * rho - 1) ** 3), 1e-12)
                    nu = 2.0
                    x, F = xt, Ft
                    cur = 1 - cur
                    improved = True
                    if rel < ftol and pred / max(F, 1e-300) < 10 * ftol:
                        return _Sol(x, F, pm)
                    break
                lam *= nu
                nu *= 2
                if lam > 1e12:
                    break
            if not improved:
                break
        return _Sol(x, F, pm)

    def nelder_mead(self, pm: ParamMap, x0, *, maxfev: int) -> _Sol:
        x0 = pm.clip(x0)

        def f(x):
            return self.F(pm, pm.project(x))

        r = minimize(f, x0, method="Nelder-Mead",
                     options={"xatol": 1e-10, "fatol": 1e-16, "maxfev": maxfev, "adaptive": True})
        x = pm.project(r.x)
        return _Sol(x, self.F(pm, x), pm)

    def evolution(self, pm: ParamMap, seed: int, maxiter: int) -> _Sol:
        lo, hi = pm.bounds()
        r = differential_evolution(
            lambda x: self.F(pm, pm.project(x)), list(zip(lo, hi)), seed=seed, maxiter=maxiter,
            popsize=12, tol=1e-10, polish=False, init="sobol",
        )
        x = pm.project(r.x)
        return _Sol(x, self.F(pm, x), pm)


# --------------------------------------------------------------------------- starts


def _pm_for(m: int, reduced: bool, ln_a_bounds, tau_bounds=(1e-6, 1e6)) -> ParamMap:
    if reduced and m > 0:
        return ParamMap(m, tuple(REDUCED_RETARDATION_TIMES_S[:m]), ln_a_bounds)
    return ParamMap(m, None, ln_a_bounds, tau_bounds)


def _from_creep(pm: ParamMap, a: float, J_rel, tau, c: float) -> np.ndarray:
    """x for wave speed a and elements given as (J'_k dimensionless, tau_k)."""
    E = c * a * a / np.asarray(J_rel, dtype=float)
    eta = E * np.asarray(tau, dtype=float)
    return pm.clip(pm.pack(a, E, eta))


def _creep_of(pm: ParamMap, x, c: float):
    a, E, eta = pm.unpack(x)
    return a, c * a * a / E, eta / E


def _tau_grids(m: int, lo: float, hi: float) -> list[np.ndarray]:
    """Log-spaced retardation times over [lo, hi]: the plain grid and shifted variants."""
    if m == 1:
        return [np.array([v]) for v in np.geomspace(lo * 3, hi / 3, 3)]
    base = np.geomspace(lo, hi, m)
    r = (hi / lo) ** (1.0 / (m - 1))
    return [base, base * r**0.5 / r**0.25 * 1.0, np.geomspace(lo * 3, hi / 3, m), base * r**-0.25]


# --------------------------------------------------------------------------- sweep


def parse_models(spec) -> list[int]:
    """'0-6', '1,3,5', '3' or an iterable of ints -> sorted list of m in 0..6."""
    if isinstance(spec, str):
        out: set[int] = set()
        for part in spec.replace(" ", "").split(","):
            if not part:
                continue
            try:
                if "-" in part:
                    a, b = part.split("-", 1)
                    lo, hi = int(a), int(b)
                    if not 0 <= lo <= hi <= MAX_M:  # before range(): "0-10**12" must not build a huge set
                        raise DataError(f"bad model list {spec!r}: ranges must be within 0..{MAX_M} (0 = EL)")
                    out.update(range(lo, hi + 1))
                else:
                    out.add(int(part.upper().lstrip("S").replace("EL", "0") or 0))
            except ValueError:
                raise DataError(f"bad model list {spec!r}: use e.g. 0-6 or 1,3,5 (0 = EL)") from None
        ms = sorted(out)
    else:
        ms = sorted(set(int(v) for v in spec))
    if not ms or ms[0] < 0 or ms[-1] > MAX_M:
        raise DataError(f"bad model list {spec!r}: m must be within 0..{MAX_M} (0 = EL)")
    return ms


def fit_sweep(
    t_s,
    h_m,
    rig: Rig,
    models: Iterable[int] | str = range(7),
    window_s: float | None = 20.0,
    method: str = "auto",
    reduced: bool = False,
    progress: Callable[[int, int, str], None] | None = None,
    initial: SweepResult | None = None,
    *,
    polish: bool = True,
    starts: int | None = None,
    seed: int = 0,
    tau_min_s: float | None = None,
    threads: int | None = None,
) -> SweepResult:
    """Calibrate EL/Sm models on a head record and rank them by AIC.

    ``t_s`` is time from the trigger (s, may start negative), ``h_m`` the head
    perturbation (m, head minus its steady pre-trigger value). ``models`` lists m
    (0 = EL). ``reduced`` adds the reduced S1r..S5r (tau fixed at 0.01, 0.1, 1, 10,
    100 s). ``progress(done, total, name)`` is called after each model. ``initial``
    (a previous SweepResult, e.g. on a shorter window) adds its parameters as starts.
    ``starts`` caps the number of coarse starts per model (None: all). ``threads``: 2 (the
    default on a machine with two or more cores) polishes two full-band candidates at
    once, 1 keeps everything in the calling thread; the result is the same either way.
    Pure computation: no I/O, no shared state; safe to call from worker threads.
    """
    if method not in METHODS:
        raise DataError(f"unknown fit method {method!r} (choose from {', '.join(METHODS)})")
    t0 = time.perf_counter()
    ms = parse_models(models) if not isinstance(models, range) else parse_models(list(models))
    t, d = prepare_window(t_s, h_m, window_s)
    n = d.size
    dt = float(t[1] - t[0])
    window = n * dt
    fs = 1.0 / dt
    band = manoeuvre_band_hz(rig)
    q = max(1, int(fs // (3.0 * band)))
    stage_c = _Stage(HeadEvaluator(rig, t[::q], band_hz="auto"), lowpass_decimate(d, q))
    stage_f = _Stage(HeadEvaluator(rig, t, band_hz=None), d) if polish else None
    if threads is None:
        threads = min(2, os.cpu_count() or 1)
    # a second full-band evaluator (same model, own buffers) polishes a second candidate in
    # a worker thread: full-band evaluations are large numpy/FFT operations that release the GIL
    stage_f2 = _Stage(stage_f.ev.fork(), d) if polish and threads > 1 else None
    evaluators = [st.ev for st in (stage_c, stage_f, stage_f2) if st is not None]

    def counts():
        return sum(e.evaluations for e in evaluators), sum(e.jacobians for e in evaluators)
    c = creep_scale_const(rig)

    a_nom = rig.nominal_wave_speed_m_s
    ln_a_bounds = (math.log(a_nom / 3.0), math.log(a_nom * 3.0))
    closure = rig.manoeuvre.closure_time_s
    tau_lo = max(2 * dt * q, closure / 10.0)
    tau_hi = max(window / 2.0, 4 * tau_lo)
    if tau_min_s is None:
        tau_min_s = TAU_MIN_FACTOR * closure
    tau_bounds = (float(tau_min_s), 1e6)
    single = method == "least-squares"
    max_starts = 1 if single else starts

    jobs = [(m, False) for m in ms]
    if reduced:
        jobs += [(m, True) for m in ms if 1 <= m <= len(REDUCED_RETARDATION_TIMES_S)]
    total = len(jobs)
    done = 0
    fits: list[ModelFit] = []
    coarse_best: dict[tuple[int, bool], _Sol] = {}
    fine_best: dict[tuple[int, bool], _Sol] = {}
    a0 = None

    def local(stage: _Stage, pm: ParamMap, x0, fine: bool) -> _Sol:
        if fine:
            return stage.lsq(pm, x0, max_nfev=40, ftol=1e-10)
        if method == "nelder-mead":
            return stage.nelder_mead(pm, x0, maxfev=1000)
        return stage.lsq(pm, x0, max_nfev=80, ftol=1e-10)

    for m, red in sorted(jobs, key=lambda j: (j[1], j[0])):
        pm = _pm_for(m, red, ln_a_bounds, tau_bounds)
        name = model_name(m, red)
        ev_before, jac_before = counts()
        if a0 is None:
            a0 = _scan_wave_speed(stage_c, _pm_for(0, False, ln_a_bounds), a_nom)
        # reference solution: the calibrated S(m-1) (EL for m = 1), else the EL scan
        ref = fine_best.get((m - 1, red)) or (fine_best.get((m - 1, False)) if m == 1 else None)
        if ref is None:
            pm0 = _pm_for(0, False, ln_a_bounds)
            ref = _Sol(pm0.pack(a0, [], []), math.nan, pm0)
        stage = stage_c
        if stage_f is not None:
            # defect correction: the coarse (band-limited, decimated) model's error w.r.t. the
            # full-band model, at the reference solution, is taken off the coarse data so that
            # the coarse minimum lands next to the full-band one.
            delta = lowpass_decimate(stage_f.ev.head(*ref.pm.unpack(ref.x)), q) - stage_c.ev.head(*ref.pm.unpack(ref.x))
            stage = _Stage(stage_c.ev, stage_c.d - delta)
        cands: list[np.ndarray] = []
        if initial is not None:
            old = initial.get(name)
            if old is not None and old.m == m and old.reduced == red:
                cands.append(pm.clip(pm.pack(old.wave_speed_m_s, old.E_pa, old.eta_pa_s)))
        if m == 0:
            cands.append(pm.pack(a0, [], []))
        elif red:
            tau = np.array(REDUCED_RETARDATION_TIMES_S[:m])
            pa, pJ, _ = _creep_of(ref.pm, ref.x, c)
            if pJ.size == m - 1:
                cands.append(_from_creep(pm, pa, list(pJ) + [1e-3], tau, c))
            for tot in (0.1, 0.5):
                cands.append(_from_creep(pm, a0 * (1 + tot) ** 0.5, np.full(m, tot / m), tau, c))
        else:
            cands.extend(_nested_starts(ref, pm, c, tau_lo, tau_hi))
            for grid in _tau_grids(m, tau_lo, tau_hi):
                cands.append(_reduced_then_full(stage, pm, grid, a0, c, ln_a_bounds, method))
        if max_starts is not None:
            cands = cands[: max(1, max_starts)]
        sols: list[_Sol] = []
        if method == "evolution" and pm.size > 1:
            s = stage.evolution(pm, seed + m, maxiter=60)
            sols.append(stage.lsq(pm, s.x, max_nfev=80, ftol=1e-10))
        for x0 in cands:
            sols.append(local(stage, pm, x0, fine=False))
        sols.sort(key=lambda s: s.F)
        if pm.size > 1 and method != "nelder-mead":
            # the winner continues on the cheap objective until it stops moving along the ridge
            sols[0] = stage.lsq(pm, sols[0].x, max_nfev=400, ftol=1e-13)
        coarse_best[(m, red)] = sols[0]
        if stage_f is not None:
            pol = [sols[0].x] + [s.x for s in sols[1:2] if s.F < sols[0].F * (1 + 1e-5)
                                 and np.max(np.abs(s.x - sols[0].x)) > 0.05]
            if len(pol) > 1 and stage_f2 is not None:
                with ThreadPoolExecutor(max_workers=1, thread_name_prefix="velab-polish") as pool:
                    fut = pool.submit(local, stage_f2, pm, pol[1], True)
                    fsols = [local(stage_f, pm, pol[0], fine=True), fut.result()]
            else:
                fsols = [local(stage_f, pm, x0, fine=True) for x0 in pol]
            fsols.sort(key=lambda s: s.F)
            best = fsols[0]
            if m >= 1 and not red and math.isfinite(ref.F) and ref.pm.m == m - 1 and best.F > ref.F:
                # guard: S(m) must not fit worse than S(m-1); start from S(m-1) with an element split,
                # and if that still ends above S(m-1) (the crawl along the flat ridge stops at a
                # relative 1e-11 or so), from S(m-1) itself: one element cut into two equal halves
                # reproduces S(m-1)'s head, and the polish only accepts steps that lower F
                for factor in (1.05, 1.0) if ref.pm.m else ():
                    s2 = local(stage_f, pm, _split_all(ref, pm, c, factor=factor)[0], fine=True)
                    if s2.F < best.F:
                        best = s2
                    if best.F <= ref.F:
                        break
            final_stage = stage_f
        else:
            best = sols[0]
            final_stage = stage_c
        fine_best[(m, red)] = best
        a, E, eta = pm.unpack(best.x)
        order = np.argsort(eta / E) if m else np.array([], dtype=int)
        res = final_stage.residuals(pm, best.x)
        ev_after, jac_after = counts()
        fits.append(ModelFit(
            name=name, m=m, k=pm.size, reduced=red, n=final_stage.d.size, F=sumsq(res) / res.size,
            wave_speed_m_s=a, E_pa=tuple(float(v) for v in E[order]), eta_pa_s=tuple(float(v) for v in eta[order]),
            lag1_autocorr=lag1(res), evaluations=ev_after - ev_before, jacobians=jac_after - jac_before,
            starts=len(sols),
        ))
        done += 1
        if progress is not None:
            progress(done, total, name)

    apply_criteria(fits)
    if stage_f is None:
        n_used = stage_c.d.size
    else:
        n_used = n
    settings = {
        "models": ms, "reduced": reduced, "polish": polish, "starts": starts, "seed": seed,
        "decimation": q, "coarse_band_hz": band, "tau_start_range_s": [tau_lo, tau_hi],
        "modulus_bounds_pa": [1e6, 1e12], "viscosity_bounds_pa_s": [1e6, 1e12],
        "wave_speed_bounds_m_s": [math.exp(ln_a_bounds[0]), math.exp(ln_a_bounds[1])],
        "warm_start": initial is not None, "friction": "linearised steady (tangent R = f Q0/(g D A^2))",
    }
    evals = counts()[0]
    result = SweepResult(
        n=n_used, window_s=window, sample_rate_hz=fs, method=method, settings=settings, models=fits,
        duration_s=time.perf_counter() - t0, evaluations=evals,
    )
    if not polish:
        result.notes.append(f"no full-band polish: F on the low-passed data decimated by {q}")
    return result


def creep_scale_const(rig: Rig) -> float:
    """rho alpha D / e: E0 = c a^2."""
    p = rig.pipe
    return p.constraint_alpha * rig.fluid.density_kg_m3 * p.inner_diameter_m / p.wall_thickness_m


def _scan_wave_speed(stage: _Stage, pm0: ParamMap, a_nom: float) -> float:
    """EL: grid scan of the wave speed over [0.5, 2] x nominal, then least squares."""
    grid = np.geomspace(a_nom / 2, a_nom * 2, 241)
    Fs = [stage.F(pm0, [math.log(a)]) for a in grid]
    i = int(np.argmin(Fs))
    # refine locally (the objective has period-aliasing minima every few tenths of a percent)
    fine = np.geomspace(grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)], 21)
    Fs = [stage.F(pm0, [math.log(a)]) for a in fine]
    a = float(fine[int(np.argmin(Fs))])
    s = stage.lsq(pm0, [math.log(a)], max_nfev=30, ftol=1e-12)
    return math.exp(s.x[0])


def _reduced_then_full(stage: _Stage, pm: ParamMap, tau, a: float, c: float, ln_a_bounds, method: str) -> np.ndarray:
    """Start on a tau grid: solve for (a, J) with tau fixed, then return the full x."""
    m = len(tau)
    pr = ParamMap(m, tuple(float(v) for v in tau), ln_a_bounds)
    best = None
    for tot in (0.15, 0.6):
        x0 = _from_creep(pr, a * (1 + tot) ** 0.5, np.full(m, tot / m), tau, c)
        s = stage.lsq(pr, x0, max_nfev=25, ftol=1e-8) if method != "nelder-mead" else stage.nelder_mead(pr, x0, maxfev=300)
        if best is None or s.F < best.F:
            best = s
    a1, E, eta = pr.unpack(best.x)
    return pm.clip(pm.pack(a1, E, eta))


def _split_all(prev: _Sol, pm: ParamMap, c: float, factor: float = 1.6) -> list[np.ndarray]:
    """Nested starts: each element of the S(m-1) solution split in two (largest J first)."""
    a, J, tau = _creep_of(prev.pm, prev.x, c)
    out = []
    for k in np.argsort(-J):
        Jn = list(J) + [J[k] / 2]
        Jn[k] = J[k] / 2
        tn = list(tau) + [tau[k] * factor]
        tn[k] = tau[k] / factor
        out.append(_from_creep(pm, a, Jn, tn, c))
    return out


def _nested_starts(prev: _Sol, pm: ParamMap, c: float, lo: float, hi: float) -> list[np.ndarray]:
    a, J, tau = _creep_of(prev.pm, prev.x, c)
    if J.size == 0:
        return []
    out = _split_all(prev, pm, c)
    ts = np.sort(tau)
    new_taus = [min(ts[0] / 8, lo), max(ts[-1] * 8, hi)]
    new_taus += [math.sqrt(x * y) for x, y in zip(ts[:-1], ts[1:])]
    small = max(1e-3, 0.05 * float(np.min(J)))
    for tn in new_taus:
        out.append(_from_creep(pm, a, list(J) + [small], list(tau) + [tn], c))
    return out


def _distinct(xs: list[np.ndarray], k: int) -> list[np.ndarray]:
    out: list[np.ndarray] = []
    for x in xs:
        if all(np.max(np.abs(x - y)) > 0.05 for y in out):
            out.append(x)
        if len(out) >= k:
            break
    return out
