"""The fit path's entry points: a recorded head record (``fit_record``), a run read back from its file
(``fit_run``) and the lead fit the recorder starts early (``fit_lead``).

What every caller -- ``velab fit``, the recorder's online fit, the GUI's re-fit -- calls, so an offline re-fit of
a run reproduces its online fit exactly. A record of one section is prepared (velab.fitting.prepare) and
calibrated as a lead fit on its first part and a continuation on the whole (velab.fitting.lead); a rig with
several transducers is fitted on every section at once (velab.fitting.sections).
"""

from __future__ import annotations

import numpy as np

from velab.fitting.lead import lead_window_s, matches, options_key
from velab.fitting.prepare import PreparedRecord, fit_prepared, prepare_record
from velab.fitting.results import SweepResult
from velab.fitting.options import FitOptions
from velab.fitting.sections import fit_run_sections, fit_sections
from velab.rig import Rig


def fit_record(t_s, head_m, trigger_time_s: float, rig: Rig, window_s: float | None, *, record_rate_hz: float,
               options: FitOptions | None = None, lead: bool | SweepResult = True, position_pct=None,
               section_heads: dict | None = None, progress=None, **choices) -> SweepResult:
    """Prepare a record (``prepare_record``) and calibrate on it: the one fit path of velab.

    ``window_s``: seconds after the trigger (None: all); ``options``: the user's choices
    (velab.fitting.options.FitOptions; ``choices`` by name change them, e.g. ``models=[3]``).
    The default search of a long enough window runs as a lead fit on its first part and a
    continuation on the whole (velab.fitting.lead). ``lead``: True (compute it here), a SweepResult
    (the recorder's, computed while the window's last part was being recorded: used if it is the
    lead this call would compute, else computed again), or False (one step; not the fit path's
    result, for comparisons). ``position_pct``: the recorded valve position on ``t_s`` (or None).
    A rig with several transducers: ``head_m`` is the valve's (``rig.head_section``), ``section_heads``
    the others' by name, and every section is fitted at once, as ``fit_run`` does (no lead)."""
    opts = FitOptions.of(options, **choices).replace(window_s=window_s)
    if len(rig.sections) > 1:
        heads = {rig.head_section.name: head_m, **(section_heads or {})}
        return fit_sections(t_s, heads, trigger_time_s, rig, window_s, opts, record_rate_hz=record_rate_hz,
                            position_pct=position_pct, progress=progress)
    rec = prepare_record(t_s, head_m, trigger_time_s, rig, window_s, record_rate_hz=record_rate_hz,
                         position_pct=position_pct)
    lw = lead_window_s(rig, rec.window_s, opts) if lead is not False else None
    if lw is None:
        return fit_prepared(rec, rig, opts, progress=progress)
    rec_lead = prepare_record(t_s, head_m, trigger_time_s, rig, lw, record_rate_hz=record_rate_hz,
                              position_pct=position_pct)
    computed = not matches(lead, rec.window_s, opts, rec_lead.describe())
    if computed:
        lead = _fit_lead_record(rec_lead, rig, rec.window_s, opts,
                                progress=_stage_progress(progress, 0, f" (lead fit, {lw:.6g} s)"))
    result = fit_prepared(rec, rig, opts, lead=lead, progress=_stage_progress(progress, 1, ""))
    result.settings = result.settings.replace(lead={**result.settings.lead, "computed_in_this_fit": computed})
    if computed:
        result.duration_s += lead.duration_s  # this call's time: both steps
    return result


def fit_lead(t_s, head_m, trigger_time_s: float, rig: Rig, window_s: float, *, record_rate_hz: float,
             options: FitOptions | None = None, position_pct=None, progress=None, **choices) -> SweepResult | None:
    """The lead fit of a ``window_s`` fit of this record (None if it has none): what ``fit_record``
    computes first, for the recorder to run as soon as the lead's part of the window is in. ``t_s``
    and ``head_m`` need only reach the end of that part."""
    opts = FitOptions.of(options, **choices).replace(window_s=window_s)
    lw = lead_window_s(rig, window_s, opts)
    if lw is None:
        return None
    if position_pct is not None:  # the recorder passes the record up to now; the lead needs its part
        position_pct = np.asarray(position_pct, dtype=float)[: np.size(t_s)]
    rec_lead = prepare_record(t_s, head_m, trigger_time_s, rig, lw, record_rate_hz=record_rate_hz,
                              position_pct=position_pct)
    return _fit_lead_record(rec_lead, rig, window_s, opts, progress=progress)


def _fit_lead_record(rec_lead: PreparedRecord, rig: Rig, window_s: float, opts: FitOptions,
                     progress=None) -> SweepResult:
    """The lead fit on its prepared record, marked with what it was made for (``matches``)."""
    lead = fit_prepared(rec_lead, rig, opts, refine="only", progress=progress)
    lead.settings = lead.settings.replace(lead_for=options_key(window_s, opts))
    return lead


def _stage_progress(progress, stage: int, suffix: str):
    """progress(done, total, name) of one of the two steps, counted over both."""
    if progress is None:
        return None
    return lambda done, total, name: progress(stage * total + done, 2 * total, name + suffix)


def fit_run(run, window_s: float | None, options: FitOptions | None = None, *, progress=None,
            **choices) -> SweepResult:
    """``fit_record`` on a run read back from its file (velab.runfiles.reader.Run): what ``velab fit`` and the
    GUI archive's re-fit call. Lost samples inside the window are refused (a gap cannot be fitted)."""
    opts = FitOptions.of(options, **choices).replace(window_s=window_s)
    if len(run.rig.sections) > 1:  # several transducers: every section at once (velab.fitting.sections)
        return fit_run_sections(run, window_s, opts, progress=progress)
    run.fit_window(window_s)  # the reader's own checks of the window (gaps, NaN), with the file's name
    return fit_record(run.time_s, run.head_m, run.trigger_time_s, run.rig, window_s,
                      record_rate_hz=run.sample_rate_hz, options=opts, position_pct=run.channels.get("valve_position"),
                      progress=progress)
