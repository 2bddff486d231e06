"""The fitted closures' uncertainty in the wall's covariance (a joint fit's nuisance parameters).

A head-only run's closure (velab.fitting.manoeuvre: six parameters) is fitted from the same record as
the wall, and its shape trades against the fast and slow elements (a slower closure smooths the
fronts as a fast element does). Held fixed, it makes the wall's standard errors and the creep band
too narrow (docs/fitting.md, "The creep function"). Here the closure parameters that are not on a
bound join the Jacobian: with the stacked rows [J_wall; V_1; ...; V_R] (each run's closure columns
V_r only on its own samples, weighted as its residuals), the wall's block of s^2 (A)^-1 is the
Schur complement (A_ww - A_wv A_vv^-1 A_vw)^-1: the wall's covariance with the closures
marginalised, inflated for the residuals' lag-1 as for one run (velab.fitting.stats.covariance).

The closure's columns are finite differences of the frequency model's head in the closure's solver
variables (velab.fitting.manoeuvre.to_solver), taken once per run at the best wall (they depend on
the wall only through the impedance, which the wall's own columns already carry to first order).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from velab.fitting.engine import HeadEvaluator, gram
from velab.fitting.offset import project, fitted, objective
from velab.fitting.closure import PARAM_NAMES, closure_bounds, closure_kappa, from_solver, to_solver
from velab.fitting.flows import closure_coupling, closure_flow
from velab.fitting.params import ParamMap, creep_const
from velab.model import ValveHeadModel
from velab.fitting.stats import covariance, lag1, standard_errors

STEP = 1e-6  # in the solver's variables (logs of beta, power and share; t50, coupling and tail as they are)


def closure_models(rig, t, d, vi, position_m: float | None = None) -> list[tuple[float, ValveHeadModel]]:
    """(step, model) per closure parameter not on a bound: the frequency model driven by the closure with
    that parameter moved by ``step`` (the flow's spectrum is the costly part, and it does not depend on
    the wall: built once per record, evaluated at every model's wall). [] for a closure not fitted.
    ``d``: the head at the valve (the orifice coupling's); ``position_m``: the head at that section
    (velab.fitting.sections; None: at the valve)."""
    if vi.source != "fitted" or not vi.params:
        return []
    v0 = np.array(to_solver([float(vi.params.get(k, 0.0)) for k in PARAM_NAMES]))
    lo, hi = closure_bounds(rig, vi.shape, closure_kappa(rig, vi))
    span = hi - lo
    t = np.asarray(t, dtype=float)
    hc = closure_coupling(t, d, rig, vi.coupling)
    out = []
    for i in range(v0.size):
        if not (lo[i] + 1e-6 * span[i] < v0[i] < hi[i] - 1e-6 * span[i]):
            continue  # on a bound: held fixed, as a wall parameter on a bound is
        v = v0.copy()
        step = STEP if v[i] + STEP <= hi[i] else -STEP
        v[i] += step
        out.append((step, ValveHeadModel(rig, t, band_hz=None, flow=closure_flow(t, hc, rig, from_solver(v)),
                                         position_m=position_m)))
    return out


def rows_at(models, ev_full: HeadEvaluator, params) -> np.ndarray:
    """d h / d v at the wall ``params`` = (a, J', tau) from ``closure_models``; ``ev_full`` the run's
    full-band evaluator (its linear friction stand-in is kept)."""
    if not models:
        return np.zeros((0, ev_full.n_t))
    h0 = ev_full.head(*params)
    rows = [(HeadEvaluator(ev_full.rig, extra_impedance=ev_full.extra_impedance, _model=vm).head(*params) - h0) / step
            for step, vm in models]
    return np.array(rows)


def closure_rows(rig, t, d, ev_full: HeadEvaluator, vi, params) -> np.ndarray:
    """d h / d v of the run's closure parameters v not on a bound (rows, on the run's grid t), at the wall
    ``params`` = (a, J', tau); ``ev_full`` the run's full-band evaluator (its linear friction stand-in is
    kept); ``vi`` the run's ValveInput. No rows for a closure that was not fitted."""
    models = closure_models(rig, t, d, vi)
    return rows_at(models, ev_full, params) if models else np.zeros((0, np.size(t)))


def _square_root(A: np.ndarray) -> np.ndarray:
    """B with B B^T = A (A symmetric, positive semi-definite): the normal matrix as the "rows" that
    velab.fitting.stats.covariance takes (it only ever forms their Gram matrix)."""
    w, Q = np.linalg.eigh(A)
    return Q * np.sqrt(np.maximum(w, 0.0))


def marginalised(f, pm: ParamMap, x, wall_rows: np.ndarray, nuisance: list[np.ndarray], slices, weights,
                 F_w: float, rho: float, rig):
    """``f`` (the joint ModelFit, its covariance conditional on the closures) with the covariance and the
    standard errors of its wall marginalised over the runs' closure parameters. ``wall_rows`` (k, N): the
    stacked weighted Jacobian of the wall; ``nuisance[r]`` the run's closure rows on its samples
    ``slices[r]``, weighted by ``weights[r]``; F_w the weighted mean square of the stacked residuals."""
    k = pm.size
    blocks = [b for b in nuisance if b.size]
    if not blocks or f.cov_x is None:
        return f
    N = wall_rows.shape[1]
    # the normal matrix of [J_wall; V_1; ...; V_R] in blocks (each V_r lives on its own run's samples only)
    K = sum(b.shape[0] for b in nuisance)
    A = np.zeros((k + K, k + K))
    A[:k, :k] = gram(wall_rows)
    i = k
    for b, sl, w in zip(nuisance, slices, weights):
        if b.size:
            V = w * b
            j = i + V.shape[0]
            A[:k, i:j] = wall_rows[:, sl] @ V.T
            A[i:j, :k] = A[:k, i:j].T
            A[i:j, i:j] = gram(V)
            i = j
    m = pm.m
    a, Jr, tau = pm.unpack(x)
    order = np.argsort(tau, kind="stable")
    perm = [0] + [1 + int(i) for i in order] + ([1 + m + int(i) for i in order] if pm.tau_free else [])
    # the wall's free parameters as the conditional covariance has them (bounds, vanished elements)
    diag = np.diag(np.array(f.cov_x, dtype=float))
    free_wall = np.zeros(k, dtype=bool)
    free_wall[perm] = np.isfinite(diag)
    free = np.concatenate([free_wall, np.ones(K, dtype=bool)])
    cov = covariance(_square_root(A), F_w, N, rho, free)[:k, :k]
    se = standard_errors(cov, m, pm.tau_free)
    c = creep_const(rig)
    E = c * a * a / Jr
    eta = E * tau

    def sel(v):
        return tuple(float(v[i]) for i in order)

    return replace(
        f, cov_x=[[float(v) for v in row] for row in cov[np.ix_(perm, perm)]], wave_speed_se_m_s=se["a"] * a,
        E_se_pa=sel([se["E"][i] * E[i] for i in range(m)]), eta_se_pa_s=sel([se["eta"][i] * eta[i] for i in range(m)]),
        tau_se_s=sel([se["tau"][i] * tau[i] if pm.tau_free else math.nan for i in range(m)]),
        J_rel_se=sel([se["J_rel"][i] * Jr[i] for i in range(m)]))


def marginalise_single(rig, t, d, vi):
    """For one run's sweep (velab.fitting.sweep.fit_sweep's ``marginalise``): f, stage, sol -> f with
    the wall's covariance marginalised over the run's fitted closure ``vi`` (no change for a flow from
    the recorded position or the rig's sigmoid). The closure was fitted from the same record; held
    fixed, it made the standard errors and the creep band too narrow on head-only data."""
    models = closure_models(rig, t, d, vi)
    if not models:
        return None

    def apply(f, stage, sol):
        if stage.ev.n_t != np.size(t):
            # the sweep ended on its coarse (decimated) stage (--no-polish): its Jacobian lives on another
            # grid; the covariance stays conditional on the closure there (docs/fitting.md)
            return f
        params = sol.pm.unpack(sol.x)
        rows = rows_at(models, stage.ev, params)
        if not rows.size:
            return f
        h, jac = stage.ev.head_jac_x(*params, sol.pm.tau_free)
        res = h - stage.d
        nb = stage.baseline  # the steady head's offset marginalised too (velab.fitting.offset)
        return marginalised(f, sol.pm, sol.x, project(jac, nb), [project(rows, nb)], [slice(None)], [1.0],
                            objective(res, nb) / res.size, lag1(fitted(res, nb)), rig)

    return apply
