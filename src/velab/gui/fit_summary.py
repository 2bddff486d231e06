"""The fit panel's result summary: the fit's Headline (velab.fitting.headline, the same summary every text
report opens with) as rich text for a QLabel (Qt-free, pure).

Best model and its support, the wave speed ± its standard error, each Kelvin-Voigt element's E, η, τ
and J with their standard errors (a table), the noise ratio in words and the warnings as sentences.
Shown in the panel itself, not in a tooltip. ``summary_html(result)`` for a fit result; ``None``
(no summary) when the result cannot give a Headline.
"""

from __future__ import annotations

import html
import math

WARN = "#8a1c14"


def _pm(value, se, fmt: str) -> str:
    """"value ± se" (se to two digits); "value (fixed)" where the fit holds it; "–" for no value."""
    try:
        v, s = float(value), float(se)
    except (TypeError, ValueError):
        return "–"
    if not math.isfinite(v):
        return "–"
    return f"{v:{fmt}} ± {s:.2g}" if math.isfinite(s) else f"{v:{fmt}} (fixed)"


def summary_html(result, warnings: bool = True) -> str | None:
    """The Headline of ``result`` as HTML (a few lines and the element table), or None; ``warnings=False``
    leaves the warnings out (the fit panel shows them on a red line of their own)."""
    try:
        from velab.fitting.headline import headline

        h = headline(result)
    except Exception:  # noqa: BLE001 - a result kind the headline does not know: the table alone
        return None
    return headline_html(h, warnings)


def headline_html(h, warnings: bool = True) -> str:
    e = html.escape
    what = f" (joint fit of {h.runs} runs)" if getattr(h, "runs", 1) > 1 else ""
    parts = [f"<b>Best model {e(h.best_model)}</b>{e(what)}: {e(h.support)}",
             f"wave speed <b>a = {e(_pm(h.wave_speed_m_s, h.wave_speed_se_m_s, '.2f'))} m/s</b> (± 1 SE)"]
    if h.elements:
        rows = ["<tr><th align='left'>KV&nbsp;</th><th>E (Pa)</th><th>η (Pa s)</th><th>τ (s)</th>"
                "<th>J (1/Pa)</th></tr>"]
        for el in h.elements:
            if el.negligible:
                rows.append(f"<tr><td>{el.index}</td><td colspan='4'>negligible element (τ {el.tau_s:.3g} s): "
                            "the model is a smaller one</td></tr>")
                continue
            cells = (_pm(el.E_pa, el.E_se_pa, ".3e"), _pm(el.eta_pa_s, el.eta_se_pa_s, ".3e"),
                     _pm(el.tau_s, el.tau_se_s, ".4g"), _pm(el.J_per_pa, el.J_se_per_pa, ".3e"))
            rows.append(f"<tr><td>{el.index}</td>" + "".join(f"<td align='right' nowrap>&nbsp;{e(c)}&nbsp;</td>"
                                                             for c in cells) + "</tr>")
        table = "<table cellspacing='0' cellpadding='1'>" + "".join(rows) + "</table>"
    elif h.best_model == "EL":
        table = "no Kelvin-Voigt element: an elastic wall"
    else:
        table = ""
    noise = f"noise ratio F/noise: {e(h.noise)}"
    if h.misfit:
        noise = f"<span style='color:{WARN}'><b>{noise}</b></span>"
    tail = [noise] + [f"<span style='color:{WARN}'>⚠ {e(w)}</span>" for w in (h.warnings if warnings else ())]
    # the words on the left, the elements' table on the right: a few lines tall whatever the model
    return ("<table cellspacing='0' cellpadding='0' width='100%'><tr>"
            f"<td width='46%' valign='top'>{'<br>'.join(parts + tail)}</td>"
            f"<td width='2%'></td><td valign='top'>{table}</td></tr></table>")


__all__ = ["headline_html", "summary_html"]
