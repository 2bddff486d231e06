"""Model selection (physics.md section 7): one place for the information criteria, the Akaike weights and
support words, the best model, the price an element must pay, and the model-averaged creep.

Every fit -- a single record, several sections of one, a campaign of runs -- ranks its models here:

- the paper's white-noise AIC, n ln F + 2k (with AICc and BIC), and the AIC of an AR(1) likelihood of the
  residuals (the default; velab.fitting.stats holds the AR(1) innovation variance it takes):

      AIC_AR1 = n ln s_e^2 - ln(1 - rho^2) + 2 (k + 1);

  a stacked fit (sections, runs) passes its parts' pooled terms (``pooled_ar1``), so that N ln s_e^2 -
  ln(1 - rho^2) is the sum of its parts' AR(1) terms;
- delta AIC, Akaike weights and Burnham & Anderson's support words under the chosen criterion
  (``SELECTIONS``: "ar1", "white"), and the best model (ties to the smaller one);
- the price of one more Kelvin-Voigt element: its two parameters cost 4 in AIC, so an element that gains less
  than ``ELEMENT_PRICE`` in n ln F does not pay (``pays``): the forward search stops there
  (velab.fitting.sweep and joint's saturation rule);
- the model-averaged creep J(t) - J0 over the Akaike weights, its band unconditional on the model (Burnham &
  Anderson 2002, section 4.3.2).

Pure functions on ModelFit-like objects (duck-typed: n, F, k, lag1_autocorr, innovation_var, ...); no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from velab.fitting.options import SELECTIONS
from velab.fitting.creep import CREEP_POINTS, Z95, CreepCurve, creep_curve, creep_range, creep_times, empty_curve

# an element's two parameters cost 2 x 2 in AIC: one that gains less than this in n ln F does not pay for itself
ELEMENT_PRICE = 4.0
# an element on a retardation-time bound (within this factor of it) that holds less than MODEL_ERROR_SHARE of the
# compliance is a model error the wall's model takes up (a closure or valve the fit does not describe, a stroke's
# position noise), not the wall's creep: docs/decisions.md
MODEL_ERROR_TAU_FACTOR = 1.2
MODEL_ERROR_SHARE = 1e-4
# the model-averaged creep is shown (report, figure) where the best model holds less than this share of the
# Akaike weight: the choice between models is then part of the uncertainty
AVERAGED_BELOW = 0.99


def check_selection(selection: str) -> None:
    """ValueError (one line) for a selection criterion not in SELECTIONS."""
    if selection not in SELECTIONS:
        raise ValueError(f"selection must be one of {SELECTIONS}, got {selection!r}")


def aic_of(neg2_loglik: float, k: int) -> float:
    """AIC = -2 ln L + 2k (``neg2_loglik`` up to a constant shared by the models compared)."""
    return neg2_loglik + 2 * k


def white_aic(n: int, F: float, k: int) -> float:
    """The paper's AIC, n ln F + 2k (F the mean squared residual: -2 ln L of white Gaussian residuals)."""
    return aic_of(n * math.log(F) if F > 0 else -math.inf, k)


def aic_ar1(n: int, k: int, innovation_var: float, rho: float) -> float:
    """The AIC of the AR(1) likelihood: n ln s_e^2 - ln(1 - rho^2) + 2 (k + 1) (rho counted)."""
    rho = float(np.clip(rho, -0.999, 0.999))
    if not innovation_var > 0:
        return -math.inf
    return n * math.log(innovation_var) - math.log(1 - rho * rho) + 2 * (k + 1)


def pooled_ar1(terms, n_total: int) -> tuple[float, float]:
    """(rho, s_e^2) of a stacked fit from its parts' AR(1) terms ``terms`` [(n_r, rho_r, s_e,r^2)], such that
    :func:`aic_ar1` of the pool is the sum of the parts' n_r ln s_e,r^2 - ln(1 - rho_r^2) plus the pool's price:
    rho the n-weighted mean of the parts', s_e^2 solved from the sum."""
    terms = list(terms)
    total = 0.0
    for n_r, rho_r, var_r in terms:
        rho_c = float(np.clip(rho_r, -0.999, 0.999))
        total += n_r * math.log(var_r) - math.log(1 - rho_c * rho_c)
    rho = float(np.clip(np.average([t[1] for t in terms], weights=[t[0] for t in terms]), -0.999, 0.999))
    return rho, math.exp((total + math.log(1 - rho * rho)) / n_total)


def pays(gain_nlnF: float) -> bool:
    """One more element pays its AIC price: it lowers n ln F by at least ELEMENT_PRICE."""
    return gain_nlnF >= ELEMENT_PRICE


def support_category(delta_aic: float) -> str:
    """Burnham & Anderson's rule of thumb for the support of a model given its delta AIC.

    0-2 substantial; 4-7 considerably less; > 10 essentially none. The gaps of the
    rule are named "moderate" (2-4) and "little" (7-10).
    """
    if delta_aic <= 2:
        return "substantial"
    if delta_aic <= 4:
        return "moderate"
    if delta_aic <= 7:
        return "considerably less"
    if delta_aic <= 10:
        return "little"
    return "essentially none"


def criterion(f, selection: str) -> float:
    """The value of ``f``'s selection criterion (comparable between fits of one record)."""
    return f.aic_ar1 if selection == "ar1" else f.aic


def apply_criteria(fits: list, selection: str = "ar1", tau_bounds: tuple[float, float] | None = None) -> None:
    """Fill AIC (white and AR(1)), AICc, BIC, delta AIC, Akaike weights and support in place.

    ``selection`` names the criterion behind delta_aic, weight and support (and the best
    model): "ar1" (default) or "white" (the paper's). A fit without an AR(1) innovation
    variance gets F (1 - rho^2), its value for the Yule-Walker rho at large n. ``tau_bounds``
    (the fit's retardation-time box): a model whose extra elements are model errors
    (:func:`model_error_elements`) is marked as the smaller model plus negligible elements, its
    support words say so (:func:`mark_model_errors`).
    """
    check_selection(selection)
    for f in fits:
        nlf = f.n * math.log(f.F) if f.F > 0 else -math.inf
        f.aic = aic_of(nlf, f.k)
        f.aicc = f.aic + (2 * f.k * (f.k + 1) / (f.n - f.k - 1) if f.n - f.k - 1 > 0 else math.inf)
        f.bic = nlf + f.k * math.log(f.n)
        rho = f.lag1_autocorr if math.isfinite(f.lag1_autocorr) else 0.0
        if not math.isfinite(f.innovation_var):
            f.innovation_var = f.F * (1 - min(rho * rho, 0.998))
        f.aic_ar1 = aic_ar1(f.n, f.k, f.innovation_var, rho)
    if not fits:
        return
    best_white = min(f.aic for f in fits)
    crit = [criterion(f, selection) for f in fits]
    best = min(crit)
    rel = np.array([math.exp(-(c - best) / 2) for c in crit])
    w = rel / rel.sum()
    for f, c, wi in zip(fits, crit, w):
        f.delta_aic = c - best
        f.delta_aic_white = f.aic - best_white
        f.weight = float(wi)
        f.support = support_category(f.delta_aic)
    if tau_bounds is not None:
        mark_model_errors(fits, *tau_bounds)


def compliance_shares(f) -> list[float]:
    """Each element's share of the model's whole compliance, J'_k / (1 + sum J'_j) (the spring's is the 1)."""
    J = [float(v) for v in (f.J_rel or ())]
    total = 1.0 + sum(v for v in J if math.isfinite(v))
    return [v / total if math.isfinite(v) else math.nan for v in J]


def model_error_elements(f, tau_min_s: float, tau_max_s: float) -> list[int]:
    """The elements of ``f`` that are model errors, not creep: on a retardation-time bound (within
    MODEL_ERROR_TAU_FACTOR of it) and holding less than MODEL_ERROR_SHARE of the compliance. An element that
    only takes up what the model of the flow or the valve leaves fits the record better (AIC is right about
    the likelihood) and says nothing of the wall."""
    out = []
    taus = f.tau_s
    for k, share in enumerate(compliance_shares(f)):
        if k >= len(taus) or not math.isfinite(share):
            continue
        tau = taus[k]
        on_bound = tau <= tau_min_s * MODEL_ERROR_TAU_FACTOR or tau >= tau_max_s / MODEL_ERROR_TAU_FACTOR
        if on_bound and share < MODEL_ERROR_SHARE:
            out.append(k)
    return out


def mark_model_errors(fits: list, tau_min_s: float, tau_max_s: float) -> None:
    """Each model whose extra elements over a smaller fitted one are model errors (:func:`model_error_elements`)
    is reported as that smaller model plus model-error elements: ``model_error_elements`` those elements'
    indices (what the fit's warning and ModelFit.note name, and what tells them from vanished ones),
    ``equivalent_to`` the smaller model (so the model-averaged creep gives its weight to that one) and its support
    "model error" -- a better fit, but not support for the wall's creep. (``negligible`` stays what the element
    buys in n ln F.)"""
    by_m = {f.m: f for f in fits if not f.reduced}
    for f in fits:
        if f.reduced or not f.m or f.equivalent_to:
            continue
        bad = model_error_elements(f, tau_min_s, tau_max_s)
        smaller = by_m.get(f.m - len(bad))
        if not bad or smaller is None or smaller is f:
            continue
        f.model_error_elements = tuple(bad)
        f.equivalent_to = smaller.name
        f.support = "model error"


def best_of(models, selection: str):
    """The model with the least criterion; ties go to the smaller model (``models`` in the order EL, S1, ...).
    Read back from a store that kept only delta AIC (by this selection), that decides."""
    if selection == "ar1":
        if all(math.isfinite(f.aic_ar1) for f in models):
            return min(models, key=lambda f: f.aic_ar1)
        if all(math.isfinite(f.delta_aic) for f in models):
            return min(models, key=lambda f: f.delta_aic)
    return min(models, key=lambda f: f.aic)


# ----------------------------------------------------------------- the model-averaged creep

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
        return empty_curve()
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
        c = creep_curve(f, t) if len(f.E_pa) else empty_curve()
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
