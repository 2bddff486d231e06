"""One record, several measurement sections: the wall fitted on every transducer's head at once
(physics.md section 12, issue 25 part 2).

The sections of one record share everything but their position and noise: one wall (a, J'_k, tau_k),
one flow at the valve (its recorded position or its closure, fitted on the valve's section, which the
orifice law couples to), one steady state. Each section's model is the head at its distance x from the
reservoir (velab.model: -Zc sinh(mu x) / cosh(mu L); the time-domain model's nodes around x,
velab.moc ``sections_m``). The likelihood is the sum of the sections' Gaussian ones, each with its own
variance: the joint fit's (velab.fitting.joint), whose sweep is reused here with the record's sections as
its parts (velab.fitting.parts; rows weighted by each section's baseline noise, then by its own F), the
closure counted once. A joint fit of several runs stacks every section of every run the same way.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from velab.fitting.adequacy import bound_message, model_error_message
from velab.fitting.campaignrun import run_heads
from velab.fitting.joint import assess_parts, pool_baseline, search_notes, search_settings
from velab.fitting.parts import Record
from velab.fitting.recordfit import stack_record
from velab.fitting.results import SweepResult
from velab.fitting.options import FitOptions
from velab.rig import Rig


@dataclass
class SectionsResult(SweepResult):
    """A SweepResult over a record's sections: ``sections`` per section (name, position_m, n, F,
    noise_ratio under the fitted wall, baseline noise, whether it disagrees)."""

    sections: list = field(default_factory=list)

    def to_dict(self) -> dict:
        d = super().to_dict()
        d["sections"] = [dict(s) for s in self.sections]
        return d


def fit_sections(t_s, heads: dict, trigger_time_s: float, rig: Rig, window_s: float | None = 20.0,
                 options: FitOptions | None = None, *, record_rate_hz: float, position_pct=None, progress=None,
                 **choices) -> SectionsResult:
    """Calibrate one wall on every section of one record. ``heads``: transducer name -> absolute head on
    ``t_s`` (one per ``rig.sections``, named as in the rig; one at the valve, whose head drives the valve's
    orifice law); ``options`` / ``choices`` as ``velab.fitting.entry.fit_record`` (every search option, the
    reduced models too). DataError (one line) for a missing or unknown section, a rig without a transducer at
    the valve, or what fit_record refuses."""
    opts = FitOptions.of(options, **choices).replace(window_s=window_s)
    t0 = time.perf_counter()  # (the record's preparation and its closure's fit included)
    record = Record("", t_s, heads, trigger_time_s, rig, window_s, record_rate_hz=record_rate_hz,
                    position_pct=position_pct, manoeuvre=opts.manoeuvre, friction=opts.friction,
                    friction_unsteady=opts.friction_unsteady)
    st = stack_record(record, opts, progress)
    sw, bounds, fits, ms, selection = st.sweep, st.bounds, st.fits, list(opts.models), opts.selection
    runs, valve_rec, vi = record.parts, record.valve.rec, record.vi
    result = SectionsResult(n=fits[0].n, window_s=valve_rec.window_s, sample_rate_hz=valve_rec.fit_rate_hz,
                            method="sections", settings={}, models=fits, selection=selection)
    best = result.best
    result.sections, result.warnings = _per_section(runs, sw.final[(best.m, best.reduced)], best)
    tm = record.shared.tm
    result.settings = {"models": ms, **search_settings(sw), "selection": selection, "sections": True,
                       "bounds": bounds.to_dict(),
                       "manoeuvre": vi.describe(), "k_nuisance": vi.k,
                       "likelihood": "sum over sections of n_s ln F_s (each section's variance its own)",
                       "friction": {"steady": tm.steady, "unsteady": tm.unsteady, "time_domain": tm.active}}
    result.record_rate_hz = valve_rec.record_rate_hz
    result.anti_alias_filter = valve_rec.filter
    pool_baseline(result, runs)
    result.adequacy["per_section"] = ("the misfit rule is applied to each section (sections[].misfit_bound, "
                                      "sections[].disagrees)")
    if best.at_bounds:
        result.warnings.append({"code": "bound", "message": bound_message(best)})
    if best.model_error_elements:
        result.warnings.append({"code": "model_error", "message": model_error_message(best)})
    result.notes.append(f"fit of {len(runs)} sections ({', '.join(f'{r.name} at {r.position_m:g} m' for r in runs)}): "
                        f"one wall, one flow at the valve ({vi.source}), each section's noise its own")
    result.notes.extend(search_notes(sw))
    result.notes.extend(sw.closure_notes)
    result.duration_s = time.perf_counter() - t0
    result.evaluations = sw.count.evaluations
    return result


def fit_run_sections(run, window_s: float | None, options: FitOptions | None = None, *, progress=None,
                     **choices) -> SectionsResult:
    """:func:`fit_sections` on a run read back from its file, every transducer of its rig (velab.fitting.entry
    .fit_run calls it for a rig with several)."""
    opts = FitOptions.of(options, **choices)
    run.fit_window(window_s)  # the reader's own checks of the window (gaps, NaN), with the file's name
    return fit_sections(run.time_s, run_heads(run), run.trigger_time_s, run.rig, window_s, opts,
                        record_rate_hz=run.sample_rate_hz, position_pct=run.channels.get("valve_position"),
                        progress=progress)


def _per_section(runs, fin, best):
    """Per section: n, F and noise ratio under the fitted wall, and the single fit's misfit rule on it (a
    transducer whose position or calibration is wrong is named)."""
    out, warnings = [], []
    for sec, ws in assess_parts(best, runs, fin, 0, "sections"):
        out.append(sec)
        warnings.extend({"code": w["code"], "message": f"section {sec['name']} ({sec['position_m']:g} m): "
                         f"{w['message']}", "section": sec["name"]} for w in ws)
    return out, warnings
