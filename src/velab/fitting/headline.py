"""The result of a fit in five seconds: what every report opens with (record, fit, joint, info, the GUI's fit panel).

``headline(result)`` takes a SweepResult (or a JointResult, a SectionsResult, a fit read back from a run file)
and returns a frozen ``Headline``: the best model and its support in words, the wave speed with its standard
error, each Kelvin-Voigt element's E, eta, tau and J with theirs, the noise ratio (F against the record's own
noise, velab.fitting.adequacy) and the fit's warnings as sentences. ``headline_lines(h, width)`` renders it as
plain text lines no wider than ``width`` (the text reports print them first; the GUI shows the same lines).
Pure: no I/O, nothing recomputed but what the result already holds.
"""

from __future__ import annotations

import math
import textwrap
from dataclasses import asdict, dataclass

from velab.fitting.adequacy import is_misfit

# the element table's width: narrower reports wrap each element on lines of their own
_TABLE_WIDTH = 93


@dataclass(frozen=True)
class Element:
    """One Kelvin-Voigt element of the best model (sorted by retardation time); SEs NaN where held fixed."""

    index: int  # 1-based, in order of tau
    E_pa: float
    E_se_pa: float
    eta_pa_s: float
    eta_se_pa_s: float
    tau_s: float
    tau_se_s: float
    J_per_pa: float
    J_se_per_pa: float
    negligible: bool = False  # buys less than the negligible gain of n ln F (the model is a smaller one)


@dataclass(frozen=True)
class Headline:
    """What a lab engineer reads first about a fit."""

    best_model: str
    support: str  # in words: the best model's Akaike weight, the next model and its support
    weight: float
    wave_speed_m_s: float
    wave_speed_se_m_s: float
    elements: tuple[Element, ...]
    noise_ratio: float | None  # F / the pretrigger baseline's noise variance; None: not known
    misfit_bound: float | None  # the largest noise ratio chance allows
    noise: str  # the noise ratio in words
    warnings: tuple[str, ...]  # one sentence each: "misfit: the best model ..."
    runs: int = 1  # runs of a joint fit (1: a single record)
    models: int = 0  # models compared

    @property
    def misfit(self) -> bool:
        return (self.noise_ratio is not None and self.misfit_bound is not None
                and math.isfinite(self.noise_ratio) and self.noise_ratio > self.misfit_bound)

    def to_dict(self) -> dict:
        """Plain data (NaN -> None) for the JSON documents."""
        def clean(v):
            if isinstance(v, float) and not math.isfinite(v):
                return None
            if isinstance(v, dict):
                return {k: clean(x) for k, x in v.items()}
            if isinstance(v, (list, tuple)):
                return [clean(x) for x in v]
            return v

        d = clean(asdict(self))
        d["misfit"] = self.misfit
        return d


def _num(v) -> float:
    try:
        v = float(v)
    except (TypeError, ValueError):
        return math.nan
    return v


def _support_words(result, best) -> str:
    others = sorted((f for f in result.models if f is not best), key=lambda f: _num(f.delta_aic))
    w = _num(best.weight)
    lead = f"Akaike weight {w:.2f}" if math.isfinite(w) else "Akaike weight -"
    if not others:
        words = "the only model fitted"
    else:
        nxt = others[0]
        d = _num(nxt.delta_aic)
        words = (f"{lead} of {len(result.models)} models; next {nxt.name}, dAIC {d:.1f} (support: {nxt.support})"
                 if math.isfinite(d) else f"{lead} of {len(result.models)} models")
    if best.note:
        words += f"; {best.note}"
    if is_misfit(result, best):
        words += "; but it does not describe the record (misfit)"
    return words


def _noise_words(ratio: float | None, bound: float | None, has_baseline: bool) -> str:
    if ratio is None or not math.isfinite(ratio):
        return ("not known: the record's baseline is too short to measure its noise" if not has_baseline
                else "not known")
    if bound is None:
        return f"{ratio:.2f}x the record's own noise"
    if ratio > bound:
        return (f"{ratio:.2f}x the record's own noise, above the {bound:.2f}x chance allows (misfit)")
    return f"{ratio:.2f}x the record's own noise (chance allows up to {bound:.2f}x)"


_WARNING_WORDS = {"misfit": "misfit", "cavitation": "cavitation", "bound": "on a bound", "model_error": "model error"}


def headline(result) -> Headline:
    """The Headline of a fit result (its best model by the result's own selection)."""
    if not result.models:
        return Headline("-", "no model fitted", math.nan, math.nan, math.nan, (), None, None, "not known",
                        tuple(f"{w.get('code', '?')}: {w.get('message', '')}" for w in result.warnings or ()),
                        models=0)
    best = result.best
    els = []
    for i, el in enumerate(best.elements(), 1):
        els.append(Element(i, el["E"], el["E_se"], el["eta"], el["eta_se"], el["tau"], el["tau_se"], el["J"],
                           el["J_se"], bool(el["negligible"])))
    ad = getattr(result, "adequacy", None) or {}
    bound = ad.get("misfit_bound")
    ratio = best.noise_ratio
    warnings = tuple(f"{_WARNING_WORDS.get(w.get('code'), w.get('code', '?'))}: {w.get('message', '')}"
                     for w in getattr(result, "warnings", None) or ())
    runs = len(getattr(result, "runs", None) or ()) or 1
    return Headline(
        best_model=best.name, support=_support_words(result, best), weight=_num(best.weight),
        wave_speed_m_s=_num(best.wave_speed_m_s), wave_speed_se_m_s=_num(best.wave_speed_se_m_s),
        elements=tuple(els), noise_ratio=ratio, misfit_bound=bound,
        noise=_noise_words(ratio, bound, getattr(result, "baseline_noise_m", None) is not None),
        warnings=warnings, runs=runs, models=len(result.models),
    )


def pm(value: float, se: float, fmt: str = ".4g", se_fmt: str = ".2g") -> str:
    """"value +- se", or "value (fixed)" when the SE is NaN (a parameter held fixed or not estimated)."""
    if not math.isfinite(value):
        return "-"
    if math.isfinite(se):
        return f"{value:{fmt}} +- {se:{se_fmt}}"
    return f"{value:{fmt}} (fixed)"


def _wrap(text: str, width: int, indent: str = "  ", more: str = "    ") -> list[str]:
    return textwrap.wrap(text, width=width, initial_indent=indent, subsequent_indent=more,
                         break_long_words=True, break_on_hyphens=False) or [indent.rstrip()]


def element_lines(h: Headline, width: int = 100) -> list[str]:
    """The best model's elements, a table (one line each) when ``width`` allows, else each wrapped to ``width``."""
    if not h.elements:
        return ["  no Kelvin-Voigt element: an elastic wall"] if h.best_model == "EL" else []
    out = []
    wide = width >= _TABLE_WIDTH
    if wide:
        out.append(f"  {'KV':<3}{'E (Pa)':>22}{'eta (Pa s)':>22}{'tau (s)':>22}{'J (1/Pa)':>22}")
    for e in h.elements:
        if e.negligible:
            out.append(f"  {e.index:<3}negligible element (tau {e.tau_s:.3g} s): the model is a smaller one")
            continue
        E, eta = pm(e.E_pa, e.E_se_pa, ".3e"), pm(e.eta_pa_s, e.eta_se_pa_s, ".3e")
        tau, J = pm(e.tau_s, e.tau_se_s, ".4g"), pm(e.J_per_pa, e.J_se_per_pa, ".3e")
        if wide:
            out.append(f"  {e.index:<3}{E:>22}{eta:>22}{tau:>22}{J:>22}")
        else:
            out += _wrap(f"KV {e.index}: E {E} Pa, eta {eta} Pa s; tau {tau} s, J {J} 1/Pa", width, "  ",
                         "        ")
    return out


def headline_lines(h: Headline, width: int = 100) -> list[str]:
    """The Headline as plain text lines, none wider than ``width`` (at least 60)."""
    width = max(60, int(width))
    what = f"joint fit of {h.runs} runs" if h.runs > 1 else "fit"
    lines = [f"RESULT ({what}): best model {h.best_model}"]
    lines += _wrap(f"support: {h.support}", width)
    a = pm(h.wave_speed_m_s, h.wave_speed_se_m_s, ".2f")
    lines.append(f"  wave speed a = {a} m/s" if len(f"  wave speed a = {a} m/s") <= width else f"  a = {a} m/s")
    lines += element_lines(h, width)
    lines += _wrap(f"noise ratio F/noise: {h.noise}", width)
    for w in h.warnings:
        lines += _wrap(f"WARNING {w}", width)
    return lines


__all__ = ["Element", "Headline", "element_lines", "headline", "headline_lines", "pm"]
