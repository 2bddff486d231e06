"""Residual diagnostics, the AR(1) likelihood, parameter uncertainties, negligible elements.

Residuals of a real fit are correlated (the model is never exact and the transducer's
noise is not white); the white-noise AIC of the paper, n ln F + 2k, then over-rewards
extra parameters. The default model choice uses the AIC of an AR(1) likelihood of the
residuals (r_t = rho r_(t-1) + e_t, e white):

    AIC_AR1 = n ln s_e^2 - ln(1 - rho^2) + 2 (k + 1),
    s_e^2   = [(1 - rho^2) r_1^2 + sum_(t>1) (r_t - rho r_(t-1))^2] / n,

rho the lag-1 autocorrelation of the residuals (Yule-Walker), k + 1 parameters (rho
counted). With white residuals (rho ~ 0) it is the paper's AIC plus 2, so differences
between models are the paper's. The effective sample size of correlated residuals is
n_eff = n (1 - rho) / (1 + rho).

Parameter uncertainties: the covariance of the least-squares estimate in the optimiser's
variables (ln a, ln J'_k, ln tau_k) is s^2 (J^T J)^-1 with s^2 = RSS / (n - k), inflated
by n / n_eff for correlated residuals (the AR(1) variance-inflation factor); standard
errors of a, E_k, eta_k, tau_k, J_k follow to first order. Parameters on a bound and
vanished elements are held fixed (no standard error).
"""

from __future__ import annotations

import math

import numpy as np

from velab.fitting.engine import dot, gram, sumsq

# An element whose removal (others fixed) raises n ln F by less than this is "negligible":
# it buys less than a twentieth of an AIC unit, nothing a record can tell from noise.
NEGLIGIBLE_GAIN = 0.1


def lag1(res: np.ndarray) -> float:
    """Lag-1 autocorrelation of the residuals (demeaned, Yule-Walker)."""
    r = np.asarray(res, dtype=float) - np.mean(res)
    d = dot(r, r)
    return float(dot(r[1:], r[:-1]) / d) if d > 0 else 0.0


def ar1_innovation_var(res: np.ndarray, rho: float) -> float:
    """s_e^2 of the exact AR(1) likelihood at the given rho (see the module docstring)."""
    r = np.asarray(res, dtype=float)
    rho = float(np.clip(rho, -0.999, 0.999))
    e = r[1:] - rho * r[:-1]
    return ((1 - rho * rho) * float(r[0]) ** 2 + sumsq(e)) / r.size


def effective_n(n: int, rho: float) -> float:
    """n (1 - rho) / (1 + rho) for positively correlated residuals, n otherwise."""
    if not rho > 0:
        return float(n)
    rho = min(rho, 0.999)
    return n * (1 - rho) / (1 + rho)


def covariance(jac_rows: np.ndarray, F: float, n: int, rho: float, free: np.ndarray) -> np.ndarray:
    """Covariance of x from the Jacobian rows (k, n) at the optimum; NaN rows/columns for fixed x."""
    k = jac_rows.shape[0]
    cov = np.full((k, k), np.nan)
    idx = np.flatnonzero(free)
    if idx.size == 0 or n <= idx.size:
        return cov
    A = gram(jac_rows[idx])
    d = np.sqrt(np.maximum(np.diag(A), 1e-300))
    As = A / np.outer(d, d)
    inv = np.linalg.pinv(As, rcond=1e-13, hermitian=True) / np.outer(d, d)
    s2 = F * n / (n - idx.size)
    inflation = n / effective_n(n, rho)
    cov[np.ix_(idx, idx)] = s2 * inflation * inv
    return cov


def standard_errors(cov: np.ndarray, m: int, tau_free: bool) -> dict:
    """Relative (log-scale) standard errors of a, J'_k, tau_k, E_k, eta_k from cov in x.

    ln E_k = const + 2 ln a - ln J'_k,  ln eta_k = ln E_k + ln tau_k,  ln J_k = -ln E_k.
    """
    k = cov.shape[0]
    fixed = np.isnan(np.diag(cov))
    cov0 = np.nan_to_num(cov)

    def sd(g):
        if np.any(fixed & (g != 0)):
            return math.nan
        v = float(g @ cov0 @ g)
        return math.sqrt(v) if v >= 0 else math.nan

    e = np.eye(k)
    out = {"a": sd(e[0]), "J_rel": [], "tau": [], "E": [], "eta": []}
    for j in range(m):
        gJ = e[1 + j]
        gE = 2 * e[0] - gJ
        out["J_rel"].append(sd(gJ))
        out["E"].append(sd(gE))
        if tau_free:
            gt = e[1 + m + j]
            out["tau"].append(sd(gt))
            out["eta"].append(sd(gE + gt))
        else:
            out["tau"].append(0.0)
            out["eta"].append(out["E"][-1])
    return out
