"""The plain-text report of a calibration sweep (``format_report``: ``velab fit``, ``velab info``): the headline
first, then the models' table, creep, bounds and notes."""

from __future__ import annotations

import math
import textwrap

from velab.fitting.adequacy import bounds_line, is_misfit
from velab.fitting.creep import creep_curve, creep_range, decades
from velab.fitting.selection import averaged_creep_shown
from velab.fitting.headline import headline, headline_lines

_SELECTION_TEXT = {
    "ar1": "AIC of an AR(1) likelihood of the residuals (robust to correlated residuals)",
    "white": "white-noise AIC n ln F + 2k (the paper's)",
}


def _pm(value: float, se: float, fmt: str) -> str:
    if math.isfinite(se):
        return f"{value:{fmt}} +- {se:.2g}"
    return f"{value:{fmt}}"


def warning_lines(result) -> list[str]:
    """One line per warning of the fit (velab.fitting.adequacy): "WARNING misfit: ..."."""
    return [f"WARNING {w.get('code', '?')}: {w.get('message', '')}" for w in getattr(result, "warnings", None) or []]


def noise_line(result) -> str:
    """The record's own noise and what chance allows the best model, or why it is not known."""
    sd = getattr(result, "baseline_noise_m", None)
    ad = getattr(result, "adequacy", None) or {}
    if sd is None:
        return ""
    bound = ad.get("misfit_bound")
    rho = getattr(result, "baseline_lag1", None)
    return (f"record noise (pretrigger baseline, {ad.get('baseline_samples', '?')} samples at the fit rate): "
            f"{sd:.3g} m, lag-1 {rho if rho is not None else math.nan:.2f}; F/noise: the model's mean squared "
            f"residual over its variance" + (f", chance allows the best model up to {bound:.2f}" if bound else ""))


def steady_head_line(result) -> str:
    """The steady head the best model took: the baseline's mean and the offset fitted with the model
    (velab.fitting.offset), against the mean's own standard error; "" without a baseline."""
    rec = (getattr(result, "settings", None) or {}).get("record") or {}
    n_b, sd = rec.get("steady_samples") or 0.0, getattr(result, "baseline_noise_m", None)
    if not (n_b > 0 and result.models and "steady_head_m" in rec):
        return ""
    off = result.best.steady_head_offset_m
    se = f" ({off / (sd / math.sqrt(n_b)):+.2g} of the mean's standard error {1e3 * sd / math.sqrt(n_b):.2g} mm)" if sd else ""
    return (f"steady head: the baseline's mean {rec['steady_head_m']:.4f} m, {result.best.name} fits it "
            f"{1e3 * off:+.3g} mm off{se}; every model fits this offset, the baseline its prior")


def _ratio(f) -> str:
    r = getattr(f, "noise_ratio", None)
    return f"{r:.3g}" if r is not None and math.isfinite(r) else "-"


def _support(result, f) -> str:
    # support among models that do not describe the record is not support: say so in the cell
    return f.support + (" (misfit)" if is_misfit(result, f) else "")


def creep_lines(result) -> list[str]:
    """The best model's retarded creep compliance J(t) - J0 with its 95 % band at the decades between
    the lower retardation-time bound and the window (velab.fitting.creep), one line each."""
    best = result.best
    if not best.m:
        return [f"creep of {best.name}: none (an elastic wall: J(t) = J0)"]
    lo, hi = creep_range(result)
    times = decades(lo, hi)
    if not times:
        return []
    c = creep_curve(best, times)
    head = (f"creep of {best.name}: J(t) - J0 (1/Pa), 95 % band from the parameter covariance "
            "(inflated for correlated residuals; fixed parameters add none)")
    if not c.has_band:
        head = f"creep of {best.name}: J(t) - J0 (1/Pa); no band (the fit holds no covariance)"
    lines = [head]
    for t, J, lo_, hi_ in zip(c.t_s, c.J_per_pa, c.lower, c.upper):
        band = f"  [{lo_:.3e}, {hi_:.3e}]" if c.has_band else ""
        lines.append(f"  t = {t:g} s: {J:.3e}{band}")
    return lines + averaged_creep_lines(result, times)


def averaged_creep_lines(result, times) -> list[str]:
    """The model-averaged J(t) - J0 at ``times`` where the choice of model is uncertain
    (velab.fitting.creep.averaged_creep_shown): its band holds the models' spread."""
    avg = averaged_creep_shown(result, times)
    if avg is None:
        return []
    c = avg.curve
    shares = ", ".join(f"{k} {v:.2f}" for k, v in sorted(avg.weights.items(), key=lambda kv: -kv[1]) if v >= 0.005)
    lines = [f"model-averaged creep (Akaike weights {shares}): J(t) - J0 (1/Pa), 95 % band with the models' spread"]
    for t, J, lo_, hi_ in zip(c.t_s, c.J_per_pa, c.lower, c.upper):
        lines.append(f"  t = {t:g} s: {J:.3e}  [{lo_:.3e}, {hi_:.3e}]")
    return lines


def statistics_lines(result, width: int = 100) -> list[str]:
    """The models compared, one line each, no wider than ``width``: k, F/noise, dAIC by the selection, weight,
    support, wave speed +- SE; a model's note on a line of its own where the row has no room for it."""
    head = (f"{'model':<6}{'k':>3}{'F/noise':>9}{'dAIC':>9}{'weight':>8}  {'support':<26}{'a (m/s)':>18}  note")
    lines = [head]
    best = result.best.name
    for f in result.models:
        mark = "*" if f.name == best else " "
        a = _pm(f.wave_speed_m_s, f.wave_speed_se_m_s, ".2f")
        row = (f"{f.name + mark:<6}{f.k:>3}{_ratio(f):>9}{f.delta_aic:>9.2f}{f.weight:>8.3f}  "
               f"{_support(result, f):<26}{a:>18}")
        note = f.note
        if note and len(row) + 2 + len(note) <= width:
            lines.append(f"{row}  {note}")
        else:
            lines.append(row.rstrip())
            if note:
                lines.extend(_wrapped(note, width, "      "))
    crit = "AIC of an AR(1) likelihood" if result.selection == "ar1" else "white-noise AIC"
    lines.extend(_wrapped(f"* best by the {crit}; F/noise: the mean squared residual over the record's noise; "
                          f"n = {result.n} samples, {result.window_s:g} s window at {result.sample_rate_hz:g} Hz "
                          "(more with -v)", width, ""))
    return lines


def _wrapped(text: str, width: int, indent: str = "") -> list[str]:
    return textwrap.wrap(text, width=width, initial_indent=indent, subsequent_indent=indent + "  ",
                         break_long_words=True, break_on_hyphens=False) or [""]


def sections_lines(result) -> list[str]:
    """The sections' table of a fit of several sections (velab.fitting.sections), each under the best model's
    wall; none for another fit."""
    sections = getattr(result, "sections", None) or []
    if not sections:
        return []
    lines = [f"sections (each under the {result.best.name} wall):",
             f"  {'section':<16}{'x (m)':>9}{'n':>8}{'F/noise':>9}{'bound':>7}  disagrees"]
    for s in sections:
        ratio, bound = s.get("noise_ratio"), s.get("misfit_bound")
        lines.append(f"  {s['name']:<16}{s['position_m']:>9.2f}{s['n']:>8}"
                     f"{'-' if ratio is None else format(ratio, '.3f'):>9}{'-' if bound is None else format(bound, '.2f'):>7}"
                     f"  {'yes' if s['disagrees'] else 'no'}")
    return lines


def format_report(result, elements: bool = True, verbose: bool = True, width: int = 100) -> str:
    """The text report: the headline (velab.fitting.headline) first; then, ``verbose``, every statistic
    (both AICs, lag-1, n_eff, J_rel, bounds, creep, the record's noise); else the models' table and the
    notes, no line wider than ``width``."""
    if not result.models:
        return "\n".join(["no model fitted", *warning_lines(result), *result.notes])
    top = headline_lines(headline(result), width)
    if not verbose:
        lines = [*top, "", *statistics_lines(result, width)]
        for note in result.notes:
            lines.extend(_wrapped(note, width))
        return "\n".join([*lines, *sections_lines(result)])
    return "\n".join([*top, "", _detail(result, elements), *sections_lines(result)])


def _detail(result, elements: bool = True) -> str:
    sel = result.selection
    warnings = warning_lines(result)
    lines = [
        f"n = {result.n} samples, window = {result.window_s:g} s from the trigger "
        f"({result.sample_rate_hz:g} Hz), method = {result.method}",
        f"model choice: {_SELECTION_TEXT.get(sel, sel)}; dAIC_w: the paper's white-noise AIC",
        *warnings,
        f"{'model':<6}{'k':>3}{'F (m^2)':>13}{'F/noise':>9}{'AIC white':>12}{'AIC AR1':>12}{'dAIC':>10}{'dAIC_w':>10}"
        f"{'weight':>7}  {'support':<27}{'a (m/s)':>17}{'lag1':>7}{'n_eff':>8}  note",
    ]
    best = result.best.name
    for f in result.models:
        mark = "*" if f.name == best else " "
        a = _pm(f.wave_speed_m_s, f.wave_speed_se_m_s, ".2f")
        lines.append(
            f"{f.name + mark:<6}{f.k:>3}{f.F:>13.6e}{_ratio(f):>9}{f.aic:>12.2f}{f.aic_ar1:>12.2f}{f.delta_aic:>10.2f}"
            f"{f.delta_aic_white:>10.2f}{f.weight:>7.3f}  {_support(result, f):<27}{a:>17}{f.lag1_autocorr:>7.3f}"
            f"{f.n_eff:>8.0f}  {f.note}"
        )
    codes = [w.get("code") for w in getattr(result, "warnings", None) or []]
    lines.append(f"best model (minimum {'AIC AR1' if sel == 'ar1' else 'AIC'}): {best}"
                 + (" -- but it does not describe the record (WARNING misfit above)" if "misfit" in codes else "")
                 + (" -- the record cavitated: no model holds there (WARNING cavitation above)"
                    if "cavitation" in codes else ""))
    if elements:
        lines.append("")
        lines.append(f"{'model':<6}{'#':>2}{'E (Pa)':>12}{'eta (Pa s)':>12}{'tau (s)':>22}{'J (1/Pa)':>12}"
                     f"{'J_rel':>11}{'gain':>9}")
        for f in result.models:
            for i, el in enumerate(f.elements(), 1):
                if el["negligible"]:
                    lines.append(f"{f.name:<6}{i:>2}  negligible element (J_rel = {el['J_rel']:.2g}, "
                                 f"buys {max(el['gain'], 0.0):.2g} of n ln F)")
                    continue
                tau = _pm(el["tau"], el["tau_se"], ".4g")
                lines.append(
                    f"{f.name:<6}{i:>2}{el['E']:>12.4e}{el['eta']:>12.4e}{tau:>22}{el['J']:>12.4e}"
                    f"{el['J_rel']:>11.3e}{el['gain']:>9.1f}"
                )
    b = result.bounds
    if b:
        src = b.get("sources", {})
        lines.append("")
        lines.append(
            f"bounds: tau in [{b['tau_min_s']:.4g}, {b['tau_max_s']:.4g}] s (tau_min: {src.get('tau_min_s', '?')}; "
            f"tau_max: {src.get('tau_max_s', '?')}); J_rel in [{b['J_rel_min']:.0e}, {b['J_rel_max']:.0e}]; "
            f"a in [{b['wave_speed_min_m_s']:.4g}, {b['wave_speed_max_m_s']:.4g}] m/s"
        )
    for f in result.models:
        if f.at_bounds:
            lines.append("on a bound: " + bounds_line(f))
    fr = result.settings.get("friction")
    if isinstance(fr, dict) and fr.get("text"):
        lines.append("friction: " + fr["text"])
    creep = creep_lines(result)
    if creep:
        lines.append("")
        lines.extend(creep)
    lag = result.best.lag1_autocorr
    lines.append("")
    lines.append(
        f"residuals of {best}: lag-1 autocorrelation {lag:.2f}, effective sample size {result.best.n_eff:.0f} of {result.n}"
        + (" -- correlated: the white-noise AIC over-rewards extra parameters" if abs(lag) > 0.2 else "")
    )
    if noise_line(result):
        lines.append(noise_line(result))
    if steady_head_line(result):
        lines.append(steady_head_line(result))
    lines.extend(result.notes)
    return "\n".join(lines)
