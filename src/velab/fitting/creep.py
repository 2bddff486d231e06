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

The model-averaged curve (``averaged_creep_of``; JSON ``creep_averaged``) weighs every model's curve by
its Akaike weight and widens the band by the models' spread (Burnham & Anderson 2002): the uncertainty
of the choice between models that describe the record alike, which no single model's band holds.

Pure computation on a ModelFit; no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

CREEP_POINTS = 50  # points of the curve in JSON, plots and the GUI (log-spaced)
Z95 = 1.959963984540054  # two-sided 95 % of the normal distribution
# the model-averaged creep is shown (report, figure) where the best model holds less than this share of the
# Akaike weight: the choice between models is then part of the uncertainty
AVERAGED_BELOW = 0.99


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


def _empty() -> CreepCurve:
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
        return _empty()
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


@dataclass(frozen=True, eq=False)
class AveragedCreep:
    """The model-averaged J(t) - J0 (``curve``, its band unconditional on the model) and the Akaike weights it
    used (``weights``: model name -> weight, renormalised over the models with a creep band), ``left_out``:
    the weight of the models without one (EL, a fit without a covariance)."""

    curve: CreepCurve
    weights: dict
    left_out: float

    def to_dict(self) -> dict:
        return {**self.curve.to_dict(), "weights": dict(self.weights), "weight_left_out": self.left_out}


def averaged_creep(weighted) -> CreepCurve:
    """Model averaging of creep curves on one time grid: ``weighted`` [(Akaike weight, CreepCurve)]. On
    theta = ln(J(t) - J0) (the scale of the bands), theta_avg = sum w_m theta_m, and the unconditional standard
    error sum w_m sqrt(var_m + (theta_m - theta_avg)^2) (Burnham & Anderson 2002, section 4.3.2, eq. 4.9):
    each model's own variance plus its spread about the average. A record that two models describe alike (a
    fourth element that trades with the fast one) gets a band holding both; one model of weight ~1 gives its
    own curve and band. Curves without a band are not averaged (the caller leaves them out); weights are
    renormalised over those given."""
    pairs = [(float(w), c) for w, c in weighted if w > 0 and c.has_band and c.t_s.size]
    if not pairs:
        return _empty()
    total = sum(w for w, _ in pairs)
    t = pairs[0][1].t_s
    theta = np.array([np.log(c.J_per_pa) for _, c in pairs])
    sd = np.array([(np.log(c.upper) - np.log(c.lower)) / (2 * Z95) for _, c in pairs])
    w = np.array([w / total for w, _ in pairs])[:, None]
    mean = (w * theta).sum(axis=0)
    se = (w * np.sqrt(sd**2 + (theta - mean) ** 2)).sum(axis=0)
    G = np.exp(mean)
    return CreepCurve(t, G, G * np.exp(-Z95 * se), G * np.exp(Z95 * se))


def averaged_creep_of(result, t_s=None, points: int = CREEP_POINTS) -> AveragedCreep:
    """The model-averaged creep of a sweep (its models' Akaike ``weight`` under its selection criterion) over
    the sweep's range (:func:`creep_range`), or on ``t_s``; ``weights`` name the models averaged."""
    lo, hi = creep_range(result)
    t = creep_times(lo, hi, points) if t_s is None else np.asarray(t_s, dtype=float).reshape(-1)
    # a model that is a smaller one plus a vanished element (``equivalent_to``) has that one's curve: its weight
    # is that model's (else the best model of material A, S3, would hold 0.88 and "S4 = S3 + ..." the rest)
    own = {f.name: 0.0 for f in result.models}
    for f in result.models:
        w = float(f.weight) if math.isfinite(f.weight) else 0.0
        own[f.equivalent_to if f.equivalent_to in own else f.name] += w
    weighted, names, left = [], {}, 0.0
    for f in result.models:
        if f.equivalent_to in own:
            continue
        w = own[f.name]
        c = creep_curve(f, t) if len(f.E_pa) else _empty()
        if c.has_band and c.t_s.size:
            weighted.append((w, c))
            names[f.name] = w
        else:
            left += w
    kept = sum(names.values())
    weights = {k: (v / kept if kept > 0 else math.nan) for k, v in names.items()}
    return AveragedCreep(averaged_creep(weighted), weights, left)


def averaged_creep_shown(result, t_s=None) -> AveragedCreep | None:
    """The model-averaged creep where the report, the figure and the GUI show it -- the choice of model uncertain
    (the best model's Akaike weight, its vanished-element twins' included, below AVERAGED_BELOW) and a band to
    show -- else None."""
    avg = averaged_creep_of(result, t_s)
    if not avg.curve.has_band or avg.weights.get(result.best.name, 0.0) >= AVERAGED_BELOW:
        return None
    return avg


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


__all__ = ["AVERAGED_BELOW", "AveragedCreep", "CreepCurve", "CREEP_POINTS", "averaged_creep", "averaged_creep_of", "averaged_creep_shown", "creep_curve", "creep_of", "creep_range", "creep_times", "decades",
           "log_creep_gradient", "retarded_compliance"]
