"""A record's measurement sections as the parts of a stacked fit (velab.fitting.joint's sweep).

One record -- one run of the rig -- holds one head per pressure transducer (``rig.sections``). Its sections
share everything but their position and their noise: the flow at the valve (the recorded position, or the
closure fitted on the valve's section, whose head the orifice law couples to: counted once), the trigger, the
steady state (each section's steady head is its own pre-trigger mean), and the time-domain model (one MOC
run gives every section's head). Each section is a *part* of the stacked fit: its prepared head, its models
at its position on three grids (coarse search, polish, fit rate), its weight (its noise, then its own F).

A fit of one record with several transducers (velab.fitting.sections) stacks one record's parts; a joint
fit of a campaign (velab.fitting.joint) stacks every part of every run, run after run.
"""

from __future__ import annotations

import math
from dataclasses import replace
from threading import Lock

import numpy as np

from velab.errors import DataError
from velab.fitting.data import lowpass_decimate
from velab.fitting.engine import HeadEvaluator
from velab.fitting.friction import TimeDomainModel, equivalent_friction, fit_rig
from velab.fitting.manoeuvre import CLOSURE_SHAPE, valve_input
from velab.fitting.nuisance import closure_models, rows_at
from velab.fitting.params import creep_const
from velab.fitting.prepare import prepare_record
from velab.fitting.refine import refine_closure
from velab.fitting.results import ModelFit, model_name
from velab.model import manoeuvre_band_hz
from velab.moc import moc_head
from velab.rig import Rig

POLISH_RATE_PER_BAND = 8.0  # the polish runs on each part's record decimated to this multiple of its band
# the window's first part, on which a fitted closure is first refined (``Record.refine``): this share of the window,
# or MIN_FIRST_PART_PERIODS wave periods 4 L / a (nominal) if that is longer, and none (the whole window) if those
# periods are more than MAX_FIRST_PART_SHARE of it. Half the window: the single path's lead fit had refined its
# closure there, and the stack refined first on the whole window had named S1 on an elastic pipe's record
# (docs/decisions.md, "One engine")
FIRST_PART_SHARE = 0.5
MAX_FIRST_PART_SHARE = 0.8
MIN_FIRST_PART_PERIODS = 5.0


class SharedTime:
    """The time-domain model of every section of one record at one wall: one MOC run gives them all (cached
    for the last wall asked; the sections' parts ask in turn, from two threads)."""

    def __init__(self, rig: Rig, t, flow, xs):
        self.tm = TimeDomainModel(rig, t, flow=flow)
        self.xs = tuple(xs)
        self._lock = Lock()
        self._key = None
        self._heads = None

    def set_flow(self, flow) -> None:
        with self._lock:
            self.tm = TimeDomainModel(self.tm.rig, self.tm.t, flow=flow)
            self._key = None

    def set_model(self, tm: TimeDomainModel) -> None:
        """The time-domain model put back (``Record.restore``)."""
        with self._lock:
            self.tm = tm
            self._key = None

    def head(self, i: int, a, J_rel, tau) -> np.ndarray:
        if len(self.xs) == 1:  # one section (at the valve): the record's own time-domain head
            return self.tm.head(a, J_rel, tau)
        key = (float(a), tuple(np.asarray(J_rel, dtype=float)), tuple(np.asarray(tau, dtype=float)))
        with self._lock:
            if key != self._key:
                tm = self.tm
                h = moc_head(tm.rig, a, np.asarray(J_rel, dtype=float), np.asarray(tau, dtype=float), tm.t,
                             friction=tm.steady, unsteady=tm.unsteady, flow=tm.flow_of(), sections_m=self.xs)
                if not np.all(np.isfinite(h)):
                    raise DataError(f"friction: the time-domain model diverged at a = {a:.4g} m/s")
                self._key, self._heads = key, h
            return self._heads[i]


class SectionTime:
    """One section's view of :class:`SharedTime`, as a part's time-domain model."""

    def __init__(self, shared: SharedTime, i: int):
        self.shared, self.i = shared, i

    def __getattr__(self, name):  # active, steady, unsteady, describe: the shared model's
        return getattr(self.shared.tm, name)

    def head(self, a, J_rel, tau) -> np.ndarray:
        return self.shared.head(self.i, a, J_rel, tau)


class Part:
    """One section of one record as a part of the stacked fit: its record, its models at its position on
    three grids, its time-domain view, its weight; the flow at the valve is the record's."""

    def __init__(self, record: "Record", name: str, x: float, rec, i: int):
        self.record, self.name, self.position_m, self.rec = record, name, x, rec
        self.rig = record.rig
        fs = 1.0 / float(rec.t[1] - rec.t[0])
        band = manoeuvre_band_hz(self.rig)
        self.qc = max(1, int(fs // (3.0 * band)))  # as the single sweep's coarse stage
        self.qm = max(1, int(fs // (POLISH_RATE_PER_BAND * band)))
        self.tm = SectionTime(record.shared, i)
        self.set_flow(record.vi)
        self.noise_var = rec.baseline_noise_m ** 2 if rec.baseline_noise_m else None
        self.var = self.noise_var  # the weight's variance: the baseline's, then the part's own F

    @property
    def n(self) -> int:
        return int(self.rec.h.size)

    @property
    def steady_n(self) -> float:
        """The baseline's samples behind its steady head at the fit rate (velab.fitting.offset's prior)."""
        return self.rec.steady_samples

    @property
    def vi(self):
        return self.record.vi

    def set_flow(self, vi) -> None:
        """The part's models driven by the record's flow at the valve ``vi``."""
        t, flow, x = self.rec.t, vi.flow, self.position_m
        self.ev_c = HeadEvaluator(self.rig, t[:: self.qc], band_hz="auto", flow=flow[:: self.qc], position_m=x)
        self.ev_m = HeadEvaluator(self.rig, t[:: self.qm], band_hz=None, flow=flow[:: self.qm], position_m=x)
        self.ev_f = HeadEvaluator(self.rig, t, band_hz=None, flow=flow, position_m=x)

    def set_friction(self, params) -> None:
        """The linear friction closest to this part's time-domain head at ``params`` (only how fast the
        defect correction converges, not where: the fitted head is the time-domain model's)."""
        if not self.tm.active:
            return
        eq = equivalent_friction(self.ev_c, params, lowpass_decimate(self.tm.head(*params), self.qc))
        self.ev_c, self.ev_m, self.ev_f = self.ev_c.fork(eq), self.ev_m.fork(eq), self.ev_f.fork(eq)

    def model_head(self, params) -> np.ndarray:
        """The head of the part's model at the fit rate: the time-domain model's with a nonlinear friction."""
        return self.tm.head(*params) if self.tm.active else self.ev_f.head(*params)

    def closure_rows(self, params) -> np.ndarray:
        """d h / d v of the record's fitted closure parameters not on a bound, at this section and the wall
        ``params`` (the closure drives every section; velab.fitting.nuisance at x). Empty if not fitted."""
        models = closure_models(self.rig, self.rec.t, self.record.valve.rec.h, self.vi, position_m=self.position_m)
        return rows_at(models, self.ev_f, params) if models else np.zeros((0, self.rec.t.size))


class Record:
    """One record (a run) and its sections as parts (module docstring). ``heads``: transducer name -> absolute
    head on ``t_s``, one per ``rig.sections`` (one at the valve, whose head drives the valve's orifice law);
    ``label`` names the record in messages (a run's path). DataError (one line, naming ``label``) for a missing
    or unknown section, a rig without a transducer at the valve, or what ``prepare_record`` refuses."""

    def __init__(self, label: str, t_s, heads: dict, trigger_time_s: float, rig: Rig, window_s, *,
                 record_rate_hz: float, position_pct=None, manoeuvre: str = "auto", friction=None,
                 friction_unsteady=None):
        self.label = label
        self.rig = rig = fit_rig(rig, friction, friction_unsteady)
        sections = rig.sections
        names = [s.name for s in sections]
        where = f"{label}: " if label else ""
        missing = [n for n in names if n not in heads]
        unknown = [n for n in heads if n not in names]
        problems = ([f"no head for {', '.join(missing)}"] if missing else []) + \
            ([f"no transducer named {', '.join(unknown)} in the rig"] if unknown else [])
        if problems:
            raise DataError(f"{where}sections: {'; '.join(problems)} (the rig's: {', '.join(names)})")
        L = rig.pipe.length_m
        at_valve = [s.name for s in sections if s.position_m == L]
        if not at_valve:
            raise DataError(f"{where}sections: the rig has no transducer at the valve (position_m = {L:g}); its "
                            f"head drives the valve's flow")
        recs = {}
        for s in sections:
            try:
                recs[s.name] = prepare_record(t_s, heads[s.name], trigger_time_s, rig, window_s,
                                              record_rate_hz=record_rate_hz, position_pct=position_pct)
            except DataError as exc:
                raise DataError(f"{where}{'' if len(sections) == 1 else f'section {s.name}: '}{exc}") from None
        valve_rec = recs[at_valve[0]]
        self.vi = valve_input(valve_rec.t, valve_rec.h, rig, valve_rec.window_s, position_pct=valve_rec.position,
                              mode=manoeuvre, shape=CLOSURE_SHAPE)
        # the model whose wall's refinement over the whole window last moved the fitted closure (``refine``)
        self.moved_with = ""
        self.shared = SharedTime(rig, valve_rec.t, self.vi.flow, [s.position_m for s in sections])
        self.parts = [Part(self, s.name, s.position_m, recs[s.name], i) for i, s in enumerate(sections)]
        self.valve = self.parts[names.index(at_valve[0])]

    def refine(self, params, bounds, first_part: bool = False, name: str = "") -> bool:
        """The fitted closure refined on the valve section's whole window with the wall ``params`` = (a, J',
        tau) as the start (velab.fitting.refine: the wall is free there, only the closure is kept); every
        part then driven by it, with its linear friction stand-in at that wall. Whether the closure moved (False
        for a flow not fitted; a closure refined before that this wall does not move keeps its flow and parts,
        and says it was refined with this wall too, as the single path's rounds do).

        ``first_part``: refined on the window's first part only (``first_part_s``) and then driving the whole
        window: the first refinement starts from a wall calibrated under the early-window closure, and refined
        from it on the whole window the closure makes up for that wall's error (docs/decisions.md, "One engine").
        ``name``: the wall's (a reduced model's "S2r"; default: by its number of elements)."""
        if self.vi.source != "fitted":
            return False
        a, J, tau = params
        E = creep_const(self.rig) * a * a / np.asarray(J)
        wall = ModelFit(name=name or model_name(len(J)), m=len(J), k=1 + 2 * len(J), reduced=False, n=self.valve.n,
                        F=math.nan, wave_speed_m_s=a, E_pa=tuple(E), eta_pa_s=tuple(E * np.asarray(tau)),
                        lag1_autocorr=0.0)
        old = self.vi
        rec = self.valve.rec
        n = self.first_part_n() if first_part else rec.t.size
        if n < rec.t.size:
            part = refine_closure(rec.t[:n], rec.h[:n], self.rig, replace(old, flow=old.flow[:n]), wall, bounds)
            self.vi = valve_input(rec.t, rec.h, self.rig, rec.window_s, closure=part)
        else:
            self.vi = refine_closure(rec.t, rec.h, self.rig, old, wall, bounds)
        moved = self.vi.params != old.params
        if not moved and old.refined_with:
            return False
        if moved:  # (a refinement on the first part is not the wall's own closure over the window)
            self.moved_with = "" if n < rec.t.size else wall.name
        self.shared.set_flow(self.vi.flow)
        for p in self.parts:
            p.set_flow(self.vi)
            p.set_friction(params)
        return moved

    def first_part_n(self) -> int:
        """The samples of the valve section's window in its first part (``first_part_s``)."""
        rec = self.valve.rec
        return int(np.count_nonzero(rec.t < first_part_s(self.rig, rec.window_s) - 0.5 * float(rec.t[1] - rec.t[0])))

    def state(self) -> tuple:
        """The record's flow at the valve and its parts' models (``restore`` puts them back)."""
        return self.vi, self.moved_with, self.shared.tm, [(p.ev_c, p.ev_m, p.ev_f) for p in self.parts]

    def restore(self, state: tuple) -> None:
        self.vi, self.moved_with, tm, evs = state
        self.shared.set_model(tm)
        for p, (ev_c, ev_m, ev_f) in zip(self.parts, evs):
            p.ev_c, p.ev_m, p.ev_f = ev_c, ev_m, ev_f


def first_part_s(rig: Rig, window_s: float) -> float:
    """The window's first part on which a closure is first refined (``Record.refine``; FIRST_PART_SHARE)."""
    shortest = MIN_FIRST_PART_PERIODS * 4.0 * rig.pipe.length_m / rig.nominal_wave_speed_m_s
    if window_s * MAX_FIRST_PART_SHARE < shortest:
        return window_s
    return max(window_s * FIRST_PART_SHARE, shortest)
