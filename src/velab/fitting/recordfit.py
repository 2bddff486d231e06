"""One record's calibration through the stacked sweep: its sections as the parts (one part for a rig with one
transducer), the fit of velab.fitting.entry.fit_record.

``stack_record`` is the engine's run on a record, shared by a record of one section (``fit_single``: its result
a single fit's SweepResult, read as every fit of one head is) and of several (velab.fitting.sections): the
sweep EL, S1, ... (velab.fitting.joint.StackedSweep), the fitted closure's refinements and continuations
(``refine_closures``), every model summarised at the fit rate with its covariance marginalised over the closure,
and the selection (velab.fitting.selection.apply_criteria).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

from velab.fitting.adequacy import assess
from velab.fitting.joint import (StackedSweep, closure_groups, refine_closures, search_options, search_settings,
                                 sweep_notes)
from velab.fitting.offset import offset
from velab.fitting.options import FitOptions
from velab.fitting.params import FitBounds, derive_bounds
from velab.fitting.parts import Record
from velab.fitting.results import SweepResult, model_name
from velab.fitting.selection import apply_criteria
from velab.fitting.settings import FitSettings
from velab.rig import Rig


@dataclass(frozen=True)
class Stacked:
    """What ``stack_record`` made: the record, the sweep after its closures' refinement, the wall's box, the
    summaries (ranked)."""

    record: Record
    sweep: StackedSweep
    bounds: FitBounds
    fits: list


def stack_record(record: Record, opts: FitOptions, progress=None) -> Stacked:
    """The record's parts calibrated together (module docstring) with the stacked search of ``opts``."""
    ms = list(opts.models)
    parts, valve_rec = record.parts, record.valve.rec
    bounds = derive_bounds(record.rig, float(valve_rec.t[1] - valve_rec.t[0]), valve_rec.window_s,
                           tau_min_s=opts.tau_min_s, tau_max_s=opts.tau_max_s)
    sw = StackedSweep(parts, bounds, opts.selection, progress, **search_options(opts))
    sw.sweep(ms, progress)
    refine_closures(sw, [record], ms)
    top = min(sw.final.values(), key=lambda f: f.loglik(parts))
    sw.reweight(top)
    groups = closure_groups(parts, [record], top)  # (at the top wall: once, not once a model)
    fits = [sw.summarise(job, sw.final[job], record.vi.k, groups) for job in sw.jobs(ms)]
    apply_criteria(fits, opts.selection, (bounds.tau_min_s, bounds.tau_max_s))
    return Stacked(record, sw, bounds, fits)


def fit_single(t_s, head_m, trigger_time_s: float, rig: Rig, window_s: float | None, opts: FitOptions, *,
               record_rate_hz: float, position_pct=None, progress=None) -> SweepResult:
    """A record of one head (a rig with one transducer) as a stack of one part: the SweepResult of a single fit
    (its settings a single fit's, its models' steady head offsets their own, the adequacy of
    velab.fitting.adequacy.assess on the prepared record). Raises DataError (one line) as prepare_record."""
    t0 = time.perf_counter()  # (the record's preparation and its closure's fit included, as a sections fit's)
    record = Record("", t_s, {rig.head_section.name: head_m}, trigger_time_s, rig, window_s,
                    record_rate_hz=record_rate_hz, position_pct=position_pct, manoeuvre=opts.manoeuvre,
                    friction=opts.friction, friction_unsteady=opts.friction_unsteady)
    st = stack_record(record, opts, progress)
    sw, part = st.sweep, record.parts[0]
    rec = part.rec
    # each model's steady head offset (velab.fitting.offset): the stacked summary leaves it in the parts
    fits = [replace(f, steady_head_offset_m=offset(sw.final[(f.m, f.reduced)].heads[0] - rec.h, part.steady_n))
            for f in st.fits]
    result = SweepResult(n=rec.h.size, window_s=rec.window_s, sample_rate_hz=rec.fit_rate_hz, method=opts.method,
                         settings=_settings(st, opts), models=fits, selection=opts.selection)
    result.evaluations = sw.count.evaluations  # (the stacked model's; the closure refinements' own fits apart)
    result.record_rate_hz = rec.record_rate_hz
    result.anti_alias_filter = rec.filter
    result.notes.extend(sweep_notes(sw, several=False))
    result.notes.append(record.vi.text)
    result.notes.extend(rec.notes)
    assess(result, rec, rig)  # noise ratios and warnings (misfit, cavitation, bound, model error)
    result.duration_s = time.perf_counter() - t0
    return result


def _settings(st: Stacked, opts: FitOptions) -> FitSettings:
    sw, record = st.sweep, st.record
    tm = record.shared.tm
    return FitSettings(
        models=list(opts.models), **search_settings(sw), tau_start_range_s=[sw.tau_lo, sw.tau_hi],
        tau_min_s=opts.tau_min_s, tau_max_s=opts.tau_max_s, bounds=st.bounds.to_dict(), selection=opts.selection,
        not_searched=[model_name(m) for m in sw.not_searched], not_continued=[model_name(*job) for job in sw.not_continued],
        friction={"steady": tm.steady, "unsteady": tm.unsteady, "time_domain": tm.active, "text": tm.describe()},
        manoeuvre=record.vi.describe(), k_nuisance=record.vi.k, record=record.valve.rec.describe())

