"""The lead fit: the default sweep searches the window's first part, then continues on the whole window.

A fit window of T seconds is calibrated in two steps (velab.fitting.entry.fit_record):

1. the *lead fit*: the full multi-start sweep (velab.fitting.sweep) on the window's first part
   (``lead_window_s``: LEAD_SHARE of it, or MIN_LEAD_PERIODS wave periods if that is longer, at most
   MAX_LEAD_SHARE of it), prepared like any record;
2. the *continuation*: every model calibrated on the whole window from the lead's optimum alone
   (coarse solve, full-band polish, friction refresh, nesting guard and hand-back as in any
   sweep, no multi-start search); a model that ended in the lead as a smaller one plus a
   vanished element is that again.

The window's last part is the transient's most damped stretch: the search finds the same basins
without it (on the time-domain truths of tests/fitting/test_fit_truths.py, two rigs, EL..S4, two noise
seeds, the same best model in every case and F within 5e-6 of a one-step sweep). The point is
*when* the work is done: the recorder starts the lead fit as soon as its part of the window is
in, while the rest is still being recorded, so that only the continuation is left when the
window closes (velab.recording.online_fit). Offline, ``velab fit`` runs both steps on the same
samples; the online fit's lead is checked against what the offline one would compute
(``matches``) and recomputed if it differs, so a re-fit reproduces the online fit exactly.

This module is light (no scipy): the recorder reads ``lead_window_s`` to know when to start the
lead. The lead applies to the default search (FitOptions.default_search: method "auto", polish on, all starts) of a
window whose first MAX_LEAD_SHARE holds at least MIN_LEAD_PERIODS wave periods 4L/a: a shorter one is
fitted in one step.
"""

from __future__ import annotations

from collections.abc import Mapping

from velab.fitting.options import FitOptions
from velab.rig import Rig

LEAD_SHARE = 0.5  # the lead fit's part of the window, when that holds MIN_LEAD_PERIODS
MAX_LEAD_SHARE = 0.8  # ... and at most this share (a window shorter than MIN_LEAD_PERIODS / 0.8: one step)
MIN_LEAD_PERIODS = 5.0  # the lead's part must hold this many wave periods 4 L / a (nominal)


def lead_window_s(rig: Rig, window_s: float, options: FitOptions) -> float | None:
    """The lead fit's window (s after the trigger) for a fit of ``window_s`` with these options, or None
    (fitted in one step: not the default search, or too short a window)."""
    if not options.default_search:
        return None
    # half the window: the recorder then has the window's second half to run the lead in, so that only the
    # continuation is left when it closes (the lead's search costs about what the continuation does)
    shortest = MIN_LEAD_PERIODS * 4.0 * rig.pipe.length_m / rig.nominal_wave_speed_m_s
    if window_s * MAX_LEAD_SHARE < shortest:
        return None
    return max(window_s * LEAD_SHARE, shortest)


def options_key(window_s: float, options: FitOptions) -> str:
    """What a lead fit was made for: the final window and the options (stored with the lead as
    ``settings["lead_for"]``; a lead made for anything else is not used)."""
    return repr((float(window_s), options.key()))


def matches(lead: object, window_s: float, options: FitOptions, record: dict) -> bool:
    """``lead`` is the lead fit of a ``window_s`` fit with these options, on the samples that
    ``record`` (the lead window's preparation, PreparedRecord.describe()) names: trigger, steady
    head, rates, window and sample count."""
    settings = getattr(lead, "settings", None)  # (a SweepResult; True/None: no lead given)
    return (isinstance(settings, Mapping) and settings.get("lead_for") == options_key(window_s, options)
            and settings.get("record") == record)
