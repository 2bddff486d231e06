"""Does the fit describe the record? Its residuals against the record's own noise (physics.md section 11).

The pretrigger baseline (steady flow, nothing moving) measures the record's noise: prepared like the
fit window (same steady head, same anti-alias filter and decimation to the fit rate) and detrended by
its mean, its variance sigma_b^2 is what a correct model leaves in F = RSS / n. Every model gets

    noise_ratio = F / sigma_b^2.

When the model is right F / sigma_b^2 is 1 within chance: F's own scatter, sqrt(2 / n_eff) with
n_eff = n (1 - rho) / (1 + rho) from the residuals' lag-1 rho, and the baseline variance's,
sqrt(2 / n_b_eff) from the baseline's lag-1. The best model's ratio beyond

    max(MISFIT_FLOOR, 1 + MISFIT_SIGMAS x sqrt(2 / n_eff + 2 / n_b_eff))

raises the warning ``misfit``: its parameters absorb what the model lacks (a wrong rig file, the
valve, air, friction) and are not the pipe's. The floor 1.5 accepts a model error of about 70 % of
the noise's standard deviation (F = sigma^2 + e^2: e = 0.7 sigma): what a correct wall model with the
real valve's imperfect flow input still leaves (docs/fitting.md). Other warnings: ``cavitation`` (the
window's head comes within ``velab.cavitation.DETECTION_MARGIN_M`` of the vapour-pressure head: no
model holds there) and ``bound`` (parameters of the best model on a bound of the box).

A warning is ``{"code": str, "message": str}`` (one plain sentence); they go into
``SweepResult.warnings`` (the JSON's top-level "warnings", the run file, the report, the GUI).
Pure functions: no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from velab.cavitation import DETECTION_MARGIN_M, cavitating, rig_temperature_c, rig_vapour_head_m
from velab.fitting.creep import creep_of
from velab.fitting.selection import compliance_shares
from velab.fitting.stats import effective_n, lag1

MIN_BASELINE_SAMPLES = 200  # at the fit rate: fewer give a noise variance too uncertain to judge by
MISFIT_FLOOR = 1.5  # F / sigma_b^2 accepted whatever n: a model error of 0.7 sigma (see the docstring)
MISFIT_SIGMAS = 4.0  # ... or this many times the ratio's chance scatter, if larger
WARNING_CODES = ("misfit", "cavitation", "bound")


@dataclass(frozen=True)
class BaselineNoise:
    """The record's noise from its pretrigger baseline, at the fit rate."""

    std_m: float | None  # None: too short a baseline (or none)
    lag1: float | None
    samples: int  # baseline samples at the fit rate that went into it

    @property
    def variance(self) -> float | None:
        return None if self.std_m is None else self.std_m ** 2


def baseline_noise(before_m, decimate=None, trim: int = 0) -> BaselineNoise:
    """The noise of the pretrigger samples ``before_m`` (head minus the steady head, m, up to the trigger).

    The last unbroken run of finite samples is taken, passed through ``decimate`` (the window's anti-alias
    filter and decimation), ``trim`` samples dropped at each end (the filter's end extension), detrended by
    its mean. Fewer than MIN_BASELINE_SAMPLES left: std None."""
    x = np.asarray(before_m, dtype=float)
    bad = np.flatnonzero(~np.isfinite(x))
    if bad.size:
        x = x[bad[-1] + 1:]  # after the last gap or NaN: the baseline next to the trigger
    if decimate is not None and x.size:
        x = np.asarray(decimate(x), dtype=float)
    if trim and x.size > 2 * trim:
        x = x[trim:-trim]
    n = int(x.size)
    if n < MIN_BASELINE_SAMPLES:
        return BaselineNoise(None, None, n)
    r = x - x.mean()
    return BaselineNoise(float(math.sqrt(float(r @ r) / (n - 1))), lag1(r), n)


def ratio_scatter(n: int, rho: float, n_base: int, rho_base: float) -> float:
    """Relative standard deviation of F / sigma_b^2 by chance alone: sqrt(2/n_eff + 2/n_b_eff)."""
    n_eff = effective_n(n, rho if math.isfinite(rho) else 0.0)
    nb_eff = effective_n(n_base, rho_base if math.isfinite(rho_base) else 0.0)
    return math.sqrt(2.0 / max(n_eff, 1.0) + 2.0 / max(nb_eff, 1.0))


def misfit_bound(n: int, rho: float, n_base: int, rho_base: float) -> float:
    """The largest noise ratio chance allows: max(MISFIT_FLOOR, 1 + MISFIT_SIGMAS x ratio_scatter)."""
    return max(MISFIT_FLOOR, 1.0 + MISFIT_SIGMAS * ratio_scatter(n, rho, n_base, rho_base))


def misfit_message(name: str, ratio: float, F: float, variance: float, bound: float) -> str:
    return (f"the best model {name} leaves residuals {ratio:.1f}x the record's noise (mean square: F = {F:.3g} m^2 "
            f"against the pretrigger baseline's {variance:.3g} m^2; chance allows {bound:.2f}x): its parameters are "
            f"not the pipe's; check the rig, the valve, air, friction")


def bounds_line(f) -> str:
    """One line for the parameters of model ``f`` that ended on a bound, grouped by bound."""
    groups: dict = {}
    for b in f.at_bounds:
        groups.setdefault((b["bound"], b["limit"], b.get("hint") or b.get("option"), b["parameter"].split("_")[0]),
                          []).append(b)
    parts = []
    for (side, limit, option, kind), bs in groups.items():
        unit = " m/s" if kind == "wave" else (" s" if kind == "tau" else "")
        names = ", ".join(b["parameter"] for b in bs)
        text = f"{names} on the {side} bound {limit:.4g}{unit}"
        parts.append(text + (f" (try {option})" if option else ""))
    return f"{f.name}: " + "; ".join(parts)


def bound_message(best) -> str:
    return f"parameters of the best model on a bound: {bounds_line(best)}"


def model_error_message(best) -> str:
    """The ``model_error`` warning: what the best model's model-error elements (``best.model_error_elements``,
    found by velab.fitting.selection.mark_model_errors) are."""
    shares = compliance_shares(best)
    parts = [f"tau = {best.tau_s[k]:.3g} s holding {shares[k]:.1e} of the compliance"
             for k in best.model_error_elements]
    return (f"{best.name} fits best through {'an element' if len(parts) == 1 else 'elements'} on a retardation-time "
            f"bound ({'; '.join(parts)}): a model error (the flow at the valve, the valve or the friction the fit "
            f"does not describe), not the wall's creep; the wall is {best.equivalent_to}'s")


def assess(result, rec, rig) -> None:
    """Fill the adequacy of ``result`` (a SweepResult fitted on the PreparedRecord ``rec``) in place:
    per model ``noise_ratio``; ``baseline_noise_m``, ``baseline_lag1``, ``adequacy`` and ``warnings``."""
    var = None if rec.baseline_noise_m is None else rec.baseline_noise_m ** 2
    for f in result.models:
        f.noise_ratio = f.F / var if var and math.isfinite(f.F) else None
    result.baseline_noise_m = rec.baseline_noise_m
    result.baseline_lag1 = rec.baseline_lag1
    warnings, adequacy = [], {"baseline_samples": int(rec.baseline_samples), "misfit_bound": None,
                              "misfit_floor": MISFIT_FLOOR, "misfit_sigmas": MISFIT_SIGMAS}
    best = result.best if result.models else None
    if var is None or not var > 0:
        why = (f"the pretrigger baseline holds {rec.baseline_samples} samples at the fit rate "
               f"(at least {MIN_BASELINE_SAMPLES} needed)" if rec.baseline_noise_m is None
               else "the pretrigger baseline has no noise (a noiseless record)")
        result.notes.append(f"no noise ratio: {why}; the fit's adequacy against the record's noise is not checked")
    elif best is not None:
        bound = misfit_bound(best.n, best.lag1_autocorr, rec.baseline_samples, rec.baseline_lag1)
        adequacy["misfit_bound"] = bound
        if best.noise_ratio is not None and best.noise_ratio > bound:
            warnings.append({"code": "misfit", "message": misfit_message(best.name, best.noise_ratio, best.F, var,
                                                                         bound)})
    # column separation: the window's absolute head near the vapour-pressure head
    hv = rig_vapour_head_m(rig)
    adequacy.update({"vapour_head_m": hv, "temperature_c": rig_temperature_c(rig),
                     "cavitation_margin_m": DETECTION_MARGIN_M,
                     "min_head_m": float(np.min(rec.h)) + rec.steady_head_m if rec.h.size else None})
    found = cavitating(rec.t, np.asarray(rec.h) + rec.steady_head_m, hv)
    if found is not None:
        warnings.append({"code": "cavitation", "message": found.message()})
    if best is not None and best.at_bounds:
        warnings.append({"code": "bound", "message": bound_message(best)})
    if best is not None and best.model_error_elements:
        warnings.append({"code": "model_error", "message": model_error_message(best)})
    note = stroke_element_note(result, rig)
    if note:
        result.notes.append(note)
    result.adequacy = adequacy
    result.warnings = warnings


STROKE_SHARE = 1e-3  # an element holding less than this share of the compliance, faster than the closure


def stroke_element_note(result, rig) -> str:
    """A note when the named model, driven by the recorded valve position, is the next smaller model plus one
    element faster than the closure that holds under STROKE_SHARE of the compliance: the position's noise
    during the stroke enters the flow and leaves a wavefront error every period that such an element fits
    (docs/fitting.md, the "position" manoeuvre); the note gives how far the two creep functions differ."""
    if ((result.settings or {}).get("manoeuvre") or {}).get("source") != "position" or not result.models:
        return ""
    best = result.best
    smaller = [f for f in result.models if not f.reduced and f.m == best.m - 1 and f.m >= 1]
    if best.reduced or not smaller or len(best.J_rel) != best.m or len(best.tau_s) != best.m:
        return ""
    small = smaller[0]
    k = int(np.argmin(best.J_rel))
    share = best.J_rel[k] / float(np.sum(best.J_rel))
    closure = rig.manoeuvre.closure_time_s
    if not (best.tau_s[k] < closure and share < STROKE_SHARE):
        return ""
    a, b = creep_of(result, best).J_per_pa, creep_of(result, small).J_per_pa
    dev = float(np.max(np.abs(a / b - 1.0))) if a.size and a.size == b.size and np.all(b > 0) else math.nan
    return (f"{best.name}'s element at tau = {best.tau_s[k]:.3g} s holds {share:.1e} of the compliance and is faster "
            f"than the closure ({closure:.3g} s): the recorded valve position's noise during the stroke can make "
            f"such an element; {best.name}'s creep function is {small.name}'s within {100 * dev:.2g} %")


def is_misfit(result, f) -> bool:
    """Model ``f`` of ``result`` leaves more than chance allows the best model (the support it is given
    among the models is then support among models that do not describe the record)."""
    bound = (getattr(result, "adequacy", None) or {}).get("misfit_bound")
    r = getattr(f, "noise_ratio", None)
    return bound is not None and r is not None and math.isfinite(r) and r > bound
