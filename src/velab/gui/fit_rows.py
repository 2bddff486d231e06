"""The fit table's rows, read from a sweep result's ``to_dict()`` (Qt-free, pure).

The result's plain-data form is read defensively: a fitter that reports more (uncertainties
such as a +- da, parameters that ended on a bound, elements that vanished) fills the extra
cells; an older result, or a stored one without those keys, leaves them empty.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

COLUMNS = ("plot", "model", "k", "F (m²)", "F/noise", "AIC", "ΔAIC", "weight", "support", "a (m/s)", "lag-1",
           "notes")


def _num(x) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return math.nan
    return v


def _fin(x) -> bool:
    return math.isfinite(_num(x))


def _pm(value: float, se, fmt: str) -> str:
    """value ± se (the uncertainty to two significant digits), or the value alone without one."""
    return f"{value:{fmt}} ± {_num(se):.2g}" if _fin(se) else f"{value:{fmt}}"


@dataclass
class ModelRow:
    name: str
    cells: tuple  # one string per column of COLUMNS (the "plot" column empty)
    best: bool
    reduced: bool
    notes: list = field(default_factory=list)
    tooltip: str = ""  # per element: tau +- se, J +- se, negligible
    negligible: tuple = ()  # per element, sorted as the result's elements


def _bound_text(b: dict) -> str:
    par = str(b.get("parameter", "?"))
    side, limit = b.get("bound", ""), _num(b.get("limit"))
    unit = " m/s" if par.startswith("wave") else (" s" if par.startswith("tau") else "")
    text = f"{par} on the {side} bound" + (f" {limit:.3g}{unit}" if math.isfinite(limit) else "")
    return text + (f" ({b['option']} moves it)" if b.get("option") else "")


def warnings_text(result) -> str:
    """The fit's warnings (velab.fitting.adequacy), one per line: "misfit: the best model ...", or ""."""
    doc = result if isinstance(result, dict) else result.to_dict()
    return "\n".join(f"{w.get('code', '?')}: {w.get('message', '')}" for w in doc.get("warnings") or []
                     if isinstance(w, dict))


def criterion(doc: dict) -> str:
    """The criterion behind ΔAIC and the best model: "AIC (AR1)" or "AIC" (the paper's white-noise AIC)."""
    return "AIC (AR1)" if doc.get("selection") == "ar1" else "AIC"


def model_rows(result) -> list[ModelRow]:
    """One row per model of ``result`` (a SweepResult, or its ``to_dict()``), in the result's order."""
    doc = result if isinstance(result, dict) else result.to_dict()
    ar1 = doc.get("selection") == "ar1"
    best = doc.get("best")
    bound = _num((doc.get("adequacy") or {}).get("misfit_bound"))
    rows = []
    for m in doc.get("models") or []:
        name = str(m.get("name", "?"))
        aic = _num(m.get("aic_ar1")) if ar1 and _fin(m.get("aic_ar1")) else _num(m.get("aic"))
        a = _num(m.get("wave_speed", m.get("wave_speed_m_s")))
        els = m.get("elements") or []
        negligible = tuple(bool(e.get("negligible", False)) for e in els)
        notes = []
        if m.get("note"):
            notes.append(str(m["note"]))
        elif any(negligible):
            k = sum(negligible)
            notes.append("negligible element" if k == 1 else f"{k} negligible elements")
        notes += [_bound_text(b) for b in (m.get("at_bounds") or []) if isinstance(b, dict)]
        tips = []
        for i, e in enumerate(els, 1):
            if e.get("negligible"):
                tips.append(f"element {i}: negligible (J_rel {_num(e.get('J_rel')):.2g})")
                continue
            tau, J = _num(e.get("tau")), _num(e.get("J"))
            tips.append(f"element {i}: τ = {_pm(tau, e.get('tau_se'), '.4g')} s, J = {_pm(J, e.get('J_se'), '.3e')} 1/Pa")
        ratio = _num(m.get("noise_ratio"))
        support = str(m.get("support", ""))
        if math.isfinite(bound) and math.isfinite(ratio) and ratio > bound:
            support += " (misfit)"  # support among models that do not describe the record
            notes.append(f"F is {ratio:.3g} x the record's noise (chance allows {bound:.2f})")
        cells = ("", name, str(m.get("k", "")), f"{_num(m.get('F')):.4g}", f"{ratio:.3g}" if math.isfinite(ratio) else "–",
                 f"{aic:.1f}", f"{_num(m.get('delta_aic')):.2f}", f"{_num(m.get('weight')):.3f}", support,
                 _pm(a, m.get("wave_speed_se"), ".2f" if _fin(m.get("wave_speed_se")) else ".1f"), f"{_num(m.get('lag1_autocorr')):.2f}", "; ".join(notes))
        rows.append(ModelRow(name, cells, name == best, bool(m.get("reduced", False)), notes, "\n".join(tips),
                             negligible))
    return rows
