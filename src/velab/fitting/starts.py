"""Starting points of the calibration: the wave-speed scan, tau grids, nested starts.

Nested starts are what make F(S(m)) <= F(S(m-1)) hold in practice as well as by the
final guard (velab.fitting.sweep): every S(m) is started from S(m-1)'s optimum with an
element split in two and with a small element added below, between and above the others,
and from S(m-1) plus a vanished element (``ParamMap.embed``), which reproduces S(m-1).
"""

from __future__ import annotations

import math

import numpy as np

from velab.fitting.parallel import map_pair
from velab.fitting.params import FitBounds, ParamMap
from velab.fitting.solvers import Sol, Stage


def scan_wave_speed(stage: Stage, pm0: ParamMap, a_nom: float) -> float:
    """EL: grid scan of the wave speed over [0.5, 2] x nominal, then least squares."""
    lo, hi = pm0.bounds()
    grid = np.geomspace(max(a_nom / 2, math.exp(lo[0])), min(a_nom * 2, math.exp(hi[0])), 241)
    Fs = [stage.F(pm0, [math.log(a)]) for a in grid]
    i = int(np.argmin(Fs))
    # refine locally (the objective has period-aliasing minima every few tenths of a percent)
    fine = np.geomspace(grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)], 21)
    Fs = [stage.F(pm0, [math.log(a)]) for a in fine]
    a = float(fine[int(np.argmin(Fs))])
    # (Gauss-Newton with its budget, not the secant of Stage.lsq_1d: this only seeds EL, whose polish
    # is solved to the end, and the seed of the time-domain friction's first correction is kept as it
    # was: the Brunone truth's S3, tests/fitting/test_fit_truths.py, lands in a worse refresh basin from a seed
    # 1e-5 away)
    s = stage.lsq(pm0, [math.log(a)], max_nfev=30, ftol=1e-12, secant=False)
    return math.exp(s.x[0])


def tau_grids(m: int, lo: float, hi: float) -> list[np.ndarray]:
    """Log-spaced retardation times over [lo, hi]: the plain grid and shifted variants."""
    if m == 1:
        return [np.array([v]) for v in np.geomspace(lo * 3, hi / 3, 3)]
    base = np.geomspace(lo, hi, m)
    r = (hi / lo) ** (1.0 / (m - 1))
    return [base, base * r**0.25, np.geomspace(lo * 3, hi / 3, m), base * r**-0.25]


# a tau-grid start solves (a, J') with tau fixed first: a start, not a result (it then races)
REDUCED_NFEV = 12


def reduced_then_full(stage: Stage, pm: ParamMap, tau, a: float, method: str) -> np.ndarray:
    """Start on a tau grid: solve for (a, J') with tau fixed, then return the full x."""
    m = len(tau)
    pr = ParamMap(m, pm.bounds_, tuple(float(v) for v in tau))
    best = None
    for tot in (0.15, 0.6):
        x0 = pr.clip(pr.pack(a * (1 + tot) ** 0.5, np.full(m, tot / m)))
        if method == "nelder-mead":
            s = stage.nelder_mead(pr, x0, maxfev=300)
        else:
            s = stage.lsq(pr, x0, max_nfev=REDUCED_NFEV, ftol=1e-8)
        if best is None or s.F < best.F:
            best = s
    a1, J, _ = pr.unpack(best.x)
    return pm.clip(pm.pack(a1, J, np.asarray(tau, dtype=float)))


def split_all(ref: Sol, pm: ParamMap, factor: float = 1.6) -> list[np.ndarray]:
    """Each element of the S(m-1) solution split in two (largest J' first), tau x/÷ factor.

    With factor 1 the split reproduces S(m-1) exactly (two equal halves of one element).
    """
    a, J, tau = ref.pm.unpack(ref.x)
    out = []
    for k in np.argsort(-J):
        Jn = np.append(J, J[k] / 2)
        Jn[k] = J[k] / 2
        tn = np.append(tau, tau[k] * factor)
        tn[k] = tau[k] / factor
        out.append(pm.project(pm.pack(a, Jn, tn)))
    return out


def nested_starts(ref: Sol, pm: ParamMap, bounds: FitBounds, lo: float, hi: float) -> list[np.ndarray]:
    """Starts of S(m) from a smaller model's solution ``ref`` (S(m-1), or any S(j), j < m)."""
    a, J, tau = ref.pm.unpack(ref.x)
    extra = pm.m - ref.pm.m
    out = []
    if J.size and extra == 1:
        out.extend(split_all(ref, pm))
    live = J[J > 1e3 * bounds.J_rel_min]
    small = max(1e-3, 0.05 * float(np.min(live))) if live.size else 1e-3
    ts = np.sort(tau)
    if ts.size:
        new_taus = [min(ts[0] / 8, lo), max(ts[-1] * 8, hi)]
        new_taus += [math.sqrt(x * y) for x, y in zip(ts[:-1], ts[1:])]
    else:
        new_taus = list(np.geomspace(lo * 3, hi / 3, 3))
    for tn in new_taus:
        if extra == 1:
            out.append(pm.project(pm.pack(a, np.append(J, small), np.append(tau, tn))))
        else:
            tnew = np.geomspace(tn, tn * 10 ** (extra - 1), extra) if tn < hi else np.geomspace(tn / 10 ** (extra - 1), tn, extra)
            out.append(pm.project(pm.pack(a, np.append(J, np.full(extra, small)), np.append(tau, tnew))))
    # the exact embedding: S(j) plus vanished elements
    out.append(pm.embed(ref.pm, ref.x))
    return out


# the race of the coarse starts: every start gets RACE_NFEV evaluations, the RACE_KEEP best distinct ones
# go on to the full budget (most starts of S4-S6 end in one of a few basins; finishing them all was
# 60 % of the coarse stage)
RACE_NFEV = 12
RACE_KEEP = 3


def fan_out(stage: Stage, fn, items: list, parallel: bool) -> list:
    """[fn(stage, item) for item in items], shared out over two threads if ``parallel``
    (velab.fitting.parallel.map_pair), each on its own fork of the stage's evaluator; the
    forks' evaluation counts are added to the stage's evaluator. Same results either way."""
    forks: list[Stage] = []

    def fork() -> Stage:
        forks.append(stage.on(stage.ev.fork(workers=1)))
        return forks[-1]

    out = map_pair(fn, items, fork, parallel)
    for f in forks:
        stage.ev.evaluations += f.ev.evaluations
        stage.ev.jacobians += f.ev.jacobians
    return out


def race_starts(stage: Stage, pm: ParamMap, starts: list[np.ndarray], max_nfev: int,
                parallel: bool = False) -> list[Sol]:
    """Coarse local solutions from ``starts``: all briefly, the best few distinct ones to ``max_nfev``
    (each start on its own, in two threads if ``parallel``: the same solutions)."""
    if len(starts) <= RACE_KEEP:
        return fan_out(stage, lambda st, x0: st.lsq(pm, x0, max_nfev=max_nfev, ftol=1e-10), starts, parallel)
    short = fan_out(stage, lambda st, x0: st.lsq(pm, x0, max_nfev=RACE_NFEV, ftol=1e-10), starts, parallel)
    short.sort(key=lambda s: s.F)
    kept = distinct([s.x for s in short], RACE_KEEP)
    out = fan_out(stage, lambda st, x: st.lsq(pm, x, max_nfev=max_nfev - RACE_NFEV, ftol=1e-10), kept, parallel)
    return out + [s for s in short if not any(s.x is x for x in kept)]


def coarse_search(stage: Stage, pm: ParamMap, starts: list[np.ndarray], method: str, seed: int, max_nfev: int,
                  parallel: bool = False) -> list[Sol]:
    """The coarse local solutions of one model from ``starts``, best first, by the fit ``method``
    (velab.fitting.options.METHODS): "nelder-mead" the simplex from every start; else the race of the starts
    (``race_starts``, to ``max_nfev``), and with "evolution" (more than one variable) also scipy's differential
    evolution over the whole box seeded with the first start (``seed``), ended by least squares. ("least-squares"
    is "auto" from one start: the caller caps ``starts``.) The single sweep's (velab.fitting.sweep) and the
    stacked one's (velab.fitting.joint), one rule; with "nelder-mead" neither continues its winner by least squares
    on the coarse grid (``continues_by_lsq``)."""
    sols: list[Sol] = []
    if method == "evolution" and pm.size > 1:
        s = stage.evolution(pm, seed, maxiter=60, x0=starts[0] if starts else None)
        sols.append(stage.lsq(pm, s.x, max_nfev=max_nfev, ftol=1e-10))
    if method == "nelder-mead":
        sols.extend(stage.nelder_mead(pm, x0) for x0 in starts)
    else:
        sols.extend(race_starts(stage, pm, starts, max_nfev, parallel=parallel))
    sols.sort(key=lambda s: s.F)
    return sols


def continues_by_lsq(method: str, pm: ParamMap) -> bool:
    """Whether the coarse search's winner goes on by least squares on the coarse grid (not the simplex's)."""
    return pm.size > 1 and method != "nelder-mead"


def cap_starts(starts: list[np.ndarray], cap: int | None) -> list[np.ndarray]:
    """At most ``cap`` starts (None: all; at least one)."""
    return starts if cap is None else starts[: max(1, cap)]


def distinct(xs: list[np.ndarray], k: int, tol: float = 0.05) -> list[np.ndarray]:
    out: list[np.ndarray] = []
    for x in xs:
        if all(np.max(np.abs(x - y)) > tol for y in out):
            out.append(x)
        if len(out) >= k:
            break
    return out


def reduce_starts(big: Sol, pm: ParamMap) -> list[np.ndarray]:
    """Starts of the smaller model ``pm`` (one element fewer) from a larger model's solution:
    each element dropped, and the two elements closest in retardation time merged into one
    (compliances added, tau their compliance-weighted geometric mean). When a larger model
    found a better optimum along a structure the smaller one can express (a vanished or a
    split element), this hands it back to the smaller model."""
    a, J, tau = big.pm.unpack(big.x)
    if J.size != pm.m + 1:
        return []
    if pm.fixed_tau:
        return [pm.project(pm.pack(a, J[:-1]))]  # reduced models nest by their last element only
    out = [pm.project(pm.pack(a, np.delete(J, k), np.delete(tau, k))) for k in range(J.size)]
    if J.size >= 2:
        lt = np.log(tau)
        order = np.argsort(lt)
        i = int(np.argmin(np.diff(lt[order])))
        k1, k2 = order[i], order[i + 1]
        Jm = J[k1] + J[k2]
        tm = math.exp((J[k1] * lt[k1] + J[k2] * lt[k2]) / Jm)
        keep = [k for k in range(J.size) if k not in (k1, k2)]
        out.append(pm.project(pm.pack(a, np.append(J[keep], Jm), np.append(tau[keep], tm))))
    return out
