"""From a calibrated point to a ModelFit: parameters in physical units, residual diagnostics,
standard errors, vanished elements, parameters on a bound."""

from __future__ import annotations

import math

import numpy as np

from velab.rig import Rig
from velab.fitting.engine import sumsq
from velab.fitting.offset import fitted, objective, offset, project
from velab.fitting.params import FitBounds, bound_hits, creep_const
from velab.fitting.results import ModelFit, model_name
from velab.fitting.solvers import Sol, Stage
from velab.fitting.stats import (NEGLIGIBLE_GAIN, ar1_innovation_var, covariance, effective_n, lag1,
                                 standard_errors)

# |ln tau_i - ln tau_j| below this: the same retardation time
SAME_TAU = 1e-3


def summarise(stage: Stage, sol: Sol, name: str, rig: Rig, bounds: FitBounds, *, evaluations: int = 0,
              jacobians: int = 0, starts: int = 0, friction: dict | None = None, head_jac=None) -> ModelFit:
    """The ModelFit of ``sol`` on ``stage`` (the final stage: its data include the friction correction);
    ``head_jac``: the stage's (head, Jacobian rows) at ``sol`` if the caller has them (not computed again)."""
    pm, x = sol.pm, np.asarray(sol.x, dtype=float)
    m = pm.m
    n = stage.d.size
    a, J, tau = pm.unpack(x)
    h, jac = head_jac if head_jac is not None else stage.ev.head_jac_x(a, J, tau, pm.tau_free)
    res = h - stage.d
    b = stage.baseline
    F = objective(res, b) / n
    # the steady head's offset fitted with the model (velab.fitting.offset): its residuals, the baseline's term
    res_b = fitted(res, b)
    base_term = F - sumsq(res_b) / n
    delta = offset(res, b) if isinstance(b, (int, float)) else 0.0  # (a stacked fit's parts: in its runs)
    res = res_b
    rho = lag1(res)
    # what each element buys: n ln(F without it / F), the others fixed
    lo, _ = pm.bounds()
    gain = np.zeros(m)
    for k in range(m):
        xk = x.copy()
        xk[1 + k] = lo[1 + k]
        Fk = stage.F(pm, xk)
        gain[k] = n * math.log(Fk / F) if F > 0 and Fk > 0 else math.inf
    negligible = gain < NEGLIGIBLE_GAIN
    hits = bound_hits(pm, x, skip_elements=set(np.flatnonzero(negligible)), order=np.argsort(tau, kind="stable"))
    # standard errors: parameters on a bound and vanished elements are held fixed
    free = np.ones(pm.size, dtype=bool)
    lo, hi = pm.bounds()
    span = hi - lo
    free &= (x > lo + 1e-6 * span) & (x < hi - 1e-6 * span)
    for k in np.flatnonzero(negligible):
        free[1 + k] = False
        if pm.tau_free:
            free[1 + m + k] = False
    cov = covariance(project(jac, b), F, n, rho, free)  # (the offset marginalised)
    se = standard_errors(cov, m, pm.tau_free)
    c = creep_const(rig)
    E = c * a * a / J
    eta = E * tau
    order = np.argsort(tau, kind="stable")
    k_neg = int(negligible.sum())
    # live elements with the same retardation time act as one (an element split in two)
    live = np.sort(np.log(tau[~negligible])) if pm.tau_free else np.array([])
    k_split = int(np.sum(np.diff(live) < SAME_TAU)) if live.size > 1 else 0
    equivalent = ""
    if k_neg + k_split:
        trailing = bool(np.all(negligible[m - k_neg:])) if pm.fixed_tau else True
        if trailing:
            m_eq = m - k_neg - k_split
            equivalent = model_name(m_eq, bool(pm.fixed_tau) and m_eq > 0)

    def sel(v):
        return tuple(float(v[i]) for i in order)

    # the covariance in x, its elements in the ModelFit's order (sorted by tau): the creep band
    # (velab.fitting.creep) is computed from it later, also on a fit read back from a run file
    perm = [0] + [1 + int(i) for i in order] + ([1 + m + int(i) for i in order] if pm.tau_free else [])
    cov_x = [[float(v) for v in row] for row in cov[np.ix_(perm, perm)]]

    tau_se = [se["tau"][i] * tau[i] if pm.tau_free else math.nan for i in range(m)]
    return ModelFit(
        name=name, m=m, k=pm.size, reduced=bool(pm.fixed_tau), n=n, F=F, wave_speed_m_s=a,
        E_pa=sel(E), eta_pa_s=sel(eta), lag1_autocorr=rho, evaluations=evaluations, jacobians=jacobians,
        starts=starts, J_rel=sel(J), innovation_var=ar1_innovation_var(res, rho) + base_term, n_eff=effective_n(n, rho),
        wave_speed_se_m_s=se["a"] * a, E_se_pa=sel([se["E"][i] * E[i] for i in range(m)]),
        eta_se_pa_s=sel([se["eta"][i] * eta[i] for i in range(m)]), tau_se_s=sel(tau_se),
        J_rel_se=sel([se["J_rel"][i] * J[i] for i in range(m)]),
        negligible=tuple(bool(negligible[i]) for i in order), element_gain=sel(gain),
        at_bounds=hits, equivalent_to=equivalent, split_elements=k_split, friction=dict(friction or {}),
        cov_x=cov_x, steady_head_offset_m=delta,
    )
