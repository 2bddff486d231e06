"""The fit path's entry points: a recorded head record (``fit_record``) and a run read back from its file
(``fit_run``).

What every caller -- ``velab fit``, the recorder's online fit, the GUI's re-fit -- calls, so an offline re-fit of
a run reproduces its online fit exactly. A record is prepared (velab.fitting.prepare) and its sections (one, or
every transducer's) are calibrated together by the stacked sweep (velab.fitting.recordfit).
"""

from __future__ import annotations

from velab.fitting.options import FitOptions
from velab.fitting.recordfit import fit_single
from velab.fitting.results import SweepResult
from velab.fitting.sections import fit_run_sections, fit_sections
from velab.rig import Rig


def fit_record(t_s, head_m, trigger_time_s: float, rig: Rig, window_s: float | None, *, record_rate_hz: float,
               options: FitOptions | None = None, position_pct=None, section_heads: dict | None = None, progress=None,
               **choices) -> SweepResult:
    """Prepare a record and calibrate on it: the one fit path of velab.

    ``window_s``: seconds after the trigger (None: all); ``options``: the user's choices
    (velab.fitting.options.FitOptions; ``choices`` by name change them, e.g. ``models=[3]``).
    ``position_pct``: the recorded valve position on ``t_s`` (or None). The record's sections are the parts
    of the stacked sweep (velab.fitting.recordfit): one for a rig with one transducer (a SweepResult), all of
    them for a rig with several (``head_m`` the valve's, ``rig.head_section``, ``section_heads`` the others'
    by name: a SectionsResult, as ``fit_run`` gives)."""
    opts = FitOptions.of(options, **choices).replace(window_s=window_s)
    if len(rig.sections) > 1:
        heads = {rig.head_section.name: head_m, **(section_heads or {})}
        return fit_sections(t_s, heads, trigger_time_s, rig, window_s, opts, record_rate_hz=record_rate_hz,
                            position_pct=position_pct, progress=progress)
    return fit_single(t_s, head_m, trigger_time_s, rig, window_s, opts, record_rate_hz=record_rate_hz,
                      position_pct=position_pct, progress=progress)


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
