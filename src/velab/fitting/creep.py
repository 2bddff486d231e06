"""The retarded creep compliance of a calibrated model and its 95 % band (physics.md section 12).

    J(t) - J0 = sum_k J_k (1 - exp(-t / tau_k)),     J_k = 1 / E_k

is what papers report of a viscoelastic wall. Its band follows from the covariance of the
optimiser's variables x = (ln a, ln J'_1..J'_m, ln tau_1..tau_m) kept on the ModelFit
(``ModelFit.cov_x``: s^2 (J^T J)^-1, inflated by n / n_eff for the residuals' AR(1), in the
order of the fit's elements, sorted by tau) by the delta method on ln(J(t) - J0), so the
band stays positive:

    var(t) = g(t)^T C g(t),   g = d ln(J(t) - J0) / dx,   95 %: (J(t) - J0) exp(+-1.96 sqrt(var))

with, since J_k = J'_k / (c a^2) (c = rho alpha D / e, velab.fitting.params.creep_const),

    d/d ln a      = -2                                      (a stiffer spring: every J_k smaller)
    d/d ln J'_k   = J_k (1 - exp(-t/tau_k)) / (J(t) - J0)
    d/d ln tau_k  = -J_k (t/tau_k) exp(-t/tau_k) / (J(t) - J0)

(c drops out: the curve and its band need only the fit.) Parameters held fixed in the
covariance (a vanished element, a parameter on a bound, the fixed tau of a reduced model)
contribute no variance: the band is conditional on them, and says nothing about an element
the fit could not see. The band is the calibration's own uncertainty (noise, correlated
residuals), not the model's: a wrong model is wrong with a narrow band.

The model-averaged curve over the models' Akaike weights is velab.fitting.selection's.

Pure computation on a ModelFit; no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

CREEP_POINTS = 50  # points of the curve in JSON, plots and the GUI (log-spaced)
Z95 = 1.959963984540054  # two-sided 95 % of the normal distribution


@dataclass(frozen=True, eq=False)  # arrays: no element-wise __eq__
class CreepCurve:
    """J(t) - J0 (1/Pa) on ``t_s`` (s) with its 95 % band; ``lower``/``upper`` are NaN without a band."""

    t_s: np.ndarray
    J_per_pa: np.ndarray
    lower: np.ndarray
    upper: np.ndarray

    @property
    def has_band(self) -> bool:
        return bool(np.all(np.isfinite(self.lower)) and np.all(np.isfinite(self.upper)) and self.t_s.size)

    def to_dict(self) -> dict:
        return {"t_s": self.t_s.tolist(), "J_per_pa": self.J_per_pa.tolist(), "lower": self.lower.tolist(),
                "upper": self.upper.tolist()}


def empty_curve() -> CreepCurve:
    z = np.zeros(0)
    return CreepCurve(z, z, z, z)


def creep_times(t_min_s: float, t_max_s: float, points: int = CREEP_POINTS) -> np.ndarray:
    """Log-spaced times from ``t_min_s`` to ``t_max_s``."""
    return np.geomspace(t_min_s, t_max_s, points)


def retarded_compliance(J_per_pa, tau_s, t_s) -> np.ndarray:
    """sum_k J_k (1 - exp(-t / tau_k)) on ``t_s`` (0 for no element)."""
    t = np.asarray(t_s, dtype=float).reshape(-1, 1)
    J = np.asarray(J_per_pa, dtype=float).reshape(1, -1)
    tau = np.asarray(tau_s, dtype=float).reshape(1, -1)
    return (J * -np.expm1(-t / tau)).sum(axis=1)


def log_creep_gradient(J_per_pa, tau_s, t_s, tau_free: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(J(t) - J0, d ln(J(t) - J0) / dx) on ``t_s``; x = (ln a, ln J'_k[, ln tau_k]) in the order given.

    The gradient has one row per time and 1 + m (+ m if ``tau_free``) columns.
    """
    t = np.asarray(t_s, dtype=float).reshape(-1, 1)
    J = np.asarray(J_per_pa, dtype=float).reshape(1, -1)
    tau = np.asarray(tau_s, dtype=float).reshape(1, -1)
    r = t / tau
    rise = J * -np.expm1(-r)  # each element's share of the creep
    G = rise.sum(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(G > 0, 1.0 / G, 0.0)[:, None]
    cols = [np.full((t.shape[0], 1), -2.0), rise * inv]
    if tau_free:
        cols.append(-J * r * np.exp(-r) * inv)
    return G, np.hstack(cols)


def _cov(fit, size: int) -> np.ndarray | None:
    """The fit's covariance in x with fixed parameters as zeros; None if it has none (or not this size)."""
    cov = getattr(fit, "cov_x", None)
    if cov is None:
        return None
    C = np.array(cov, dtype=float)
    if C.shape != (size, size):
        return None
    fixed = ~np.isfinite(np.diag(C))
    if fixed.all():
        return None  # the covariance could not be computed (no free parameter, too few samples)
    C[fixed, :] = 0.0
    C[:, fixed] = 0.0
    return np.nan_to_num(C, nan=0.0)


def creep_curve(fit, t_s=None, *, t_min_s: float | None = None, t_max_s: float | None = None,
                points: int = CREEP_POINTS) -> CreepCurve:
    """J(t) - J0 of ``fit`` (a ModelFit) with its 95 % band, on ``t_s`` or ``points`` log-spaced times
    from ``t_min_s`` (the fit's lower retardation-time bound: the shortest time the record resolves)
    to ``t_max_s`` (the window). EL (no element): an empty curve. A fit without a covariance (stored
    before it was kept, or not computable): the curve with NaN bounds."""
    m = len(fit.E_pa)
    if m == 0:
        return empty_curve()
    E = np.asarray(fit.E_pa, dtype=float)
    J = 1.0 / E
    tau = np.asarray(fit.eta_pa_s, dtype=float) / E
    if t_s is None:
        if t_min_s is None or t_max_s is None:
            raise ValueError("creep_curve: give t_s or both t_min_s and t_max_s")
        t_s = creep_times(t_min_s, t_max_s, points)
    t = np.asarray(t_s, dtype=float).reshape(-1)
    tau_free = not getattr(fit, "reduced", False)
    G, g = log_creep_gradient(J, tau, t, tau_free)
    C = _cov(fit, g.shape[1])
    if C is None:
        nan = np.full(t.size, np.nan)
        return CreepCurve(t, G, nan, nan.copy())
    var = np.einsum("ij,jk,ik->i", g, C, g)
    sd = np.sqrt(np.maximum(var, 0.0))
    return CreepCurve(t, G, G * np.exp(-Z95 * sd), G * np.exp(Z95 * sd))


def creep_range(result) -> tuple[float, float]:
    """(t_min, t_max) of a sweep's creep curves: its lower retardation-time bound to its window.

    A document without bounds (stored before they were kept) starts at a thousandth of the window."""
    window = float(getattr(result, "window_s", math.nan))
    lo = (getattr(result, "bounds", None) or {}).get("tau_min_s")
    if not (math.isfinite(window) and window > 0):
        window = 20.0
    lo = float(lo) if lo is not None and math.isfinite(float(lo)) and 0 < float(lo) < window else window * 1e-3
    return lo, window


def creep_of(result, fit, t_s=None, points: int = CREEP_POINTS) -> CreepCurve:
    """The creep curve of ``fit`` (one of ``result``'s models) over the sweep's range (:func:`creep_range`)."""
    lo, hi = creep_range(result)
    return creep_curve(fit, t_s, t_min_s=lo, t_max_s=hi, points=points)


def decades(t_min_s: float, t_max_s: float) -> list[float]:
    """The powers of ten within [t_min_s, t_max_s] (the report's times)."""
    if not (t_min_s > 0 and t_max_s >= t_min_s):
        return []
    k0, k1 = math.ceil(math.log10(t_min_s) - 1e-9), math.floor(math.log10(t_max_s) + 1e-9)
    return [10.0 ** k for k in range(k0, k1 + 1)]


__all__ = ["CreepCurve", "CREEP_POINTS", "Z95", "creep_curve", "creep_of", "creep_range", "creep_times", "decades",
           "empty_curve", "log_creep_gradient", "retarded_compliance"]
