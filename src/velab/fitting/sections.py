"""One record, several measurement sections: the wall fitted on every transducer's head at once
(physics.md section 12, issue 25 part 2).

The sections of one record share everything but their position and noise: one wall (a, J'_k, tau_k),
one flow at the valve (its recorded position or its closure, fitted on the valve's section, which the
orifice law couples to), one steady state. Each section's model is the head at its distance x from the
reservoir (velab.model: -Zc sinh(mu x) / cosh(mu L); the time-domain model's nodes around x,
velab.moc ``sections_m``). The likelihood is the sum of the sections' Gaussian ones, each with its own
variance: the joint fit's (velab.fitting.joint), whose sweep is reused here with one "run" per section
(its rows weighted by its baseline noise, then by its own F), the closure counted once.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from threading import Lock

import numpy as np

from velab.errors import DataError
from velab.fitting.adequacy import bound_message
from velab.fitting.data import lowpass_decimate
from velab.fitting.engine import HeadEvaluator, sumsq
from velab.fitting.friction import TimeDomainModel, equivalent_friction, fit_rig
from velab.fitting.joint import REFINE_PASSES, _JointSweep, _first_pass_best, assess_part
from velab.fitting.manoeuvre import valve_input
from velab.fitting.nuisance import closure_models, marginalised, rows_at
from velab.fitting.params import creep_const, derive_bounds
from velab.fitting.prepare import prepare_record
from velab.fitting.refine import refine_closure
from velab.fitting.results import SELECTIONS, ModelFit, SweepResult, apply_criteria, model_name
from velab.fitting.stats import lag1
from velab.fitting.sweep import MAX_M, parse_models
from velab.model import manoeuvre_band_hz
from velab.moc import moc_head
from velab.rig import Rig

POLISH_RATE_PER_BAND = 8.0  # as the joint fit's polish grid


@dataclass
class SectionsResult(SweepResult):
    """A SweepResult over a record's sections: ``sections`` per section (name, position_m, n, F,
    noise_ratio under the fitted wall, baseline noise, whether it disagrees)."""

    sections: list = field(default_factory=list)

    def to_dict(self) -> dict:
        d = super().to_dict()
        d["sections"] = [dict(s) for s in self.sections]
        return d

    def report(self, elements: bool = True) -> str:
        """The single fit's report and the sections' table (each under the best model's wall)."""
        lines = [f"sections (each under the {self.best.name} wall):",
                 f"  {'section':<16}{'x (m)':>9}{'n':>8}{'F/noise':>9}{'bound':>7}  disagrees"]
        for s in self.sections:
            ratio, bound = s.get("noise_ratio"), s.get("misfit_bound")
            lines.append(f"  {s['name']:<16}{s['position_m']:>9.2f}{s['n']:>8}"
                         f"{'-' if ratio is None else format(ratio, '.3f'):>9}{'-' if bound is None else format(bound, '.2f'):>7}"
                         f"  {'yes' if s['disagrees'] else 'no'}")
        return super().report(elements) + "\n" + "\n".join(lines)


class _SharedTime:
    """The time-domain model of every section at one wall: one MOC run gives them all (cached for the
    last wall asked; the sections' models ask in turn, from two threads)."""

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

    def head(self, i: int, a, J_rel, tau) -> np.ndarray:
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


class _SectionTime:
    """One section's view of :class:`_SharedTime`, as a run's TimeDomainModel is used by the joint sweep."""

    def __init__(self, shared: _SharedTime, i: int):
        self.shared, self.i = shared, i

    def __getattr__(self, name):  # active, steady, unsteady, describe: the shared model's
        return getattr(self.shared.tm, name)

    def head(self, a, J_rel, tau) -> np.ndarray:
        return self.shared.head(self.i, a, J_rel, tau)


@dataclass(frozen=True)
class _Source:
    path: str  # the section's name: what the joint sweep's messages name


class _SectionRun:
    """One section as a run of the joint sweep: its record, models at its position on three grids, time-domain
    view, weight; the flow at the valve is the record's (shared)."""

    def __init__(self, name: str, x: float, rec, rig: Rig, vi, shared: _SharedTime, i: int):
        self.src = _Source(name)
        self.name, self.position_m = name, x
        self.rec, self.rig, self.vi = rec, rig, vi
        fs = 1.0 / float(rec.t[1] - rec.t[0])
        band = manoeuvre_band_hz(rig)
        self.qc = max(1, int(fs // (3.0 * band)))
        self.qm = max(1, int(fs // (POLISH_RATE_PER_BAND * band)))
        self.tm = _SectionTime(shared, i)
        self.set_flow(vi)
        self.noise_var = rec.baseline_noise_m ** 2 if rec.baseline_noise_m else None
        self.var = self.noise_var

    @property
    def n(self) -> int:
        return int(self.rec.h.size)

    def set_flow(self, vi) -> None:
        self.vi = vi
        t, flow, x = self.rec.t, vi.flow, self.position_m
        self.ev_c = HeadEvaluator(self.rig, t[:: self.qc], band_hz="auto", flow=flow[:: self.qc], position_m=x)
        self.ev_m = HeadEvaluator(self.rig, t[:: self.qm], band_hz=None, flow=flow[:: self.qm], position_m=x)
        self.ev_f = HeadEvaluator(self.rig, t, band_hz=None, flow=flow, position_m=x)

    def set_friction(self, params) -> None:
        if not self.tm.active:
            return
        eq = equivalent_friction(self.ev_c, params, lowpass_decimate(self.tm.head(*params), self.qc))
        self.ev_c, self.ev_m, self.ev_f = self.ev_c.fork(eq), self.ev_m.fork(eq), self.ev_f.fork(eq)

    def model_head(self, params) -> np.ndarray:
        return self.tm.head(*params) if self.tm.active else self.ev_f.head(*params)


def fit_sections(t_s, heads: dict, trigger_time_s: float, rig: Rig, window_s: float | None = 20.0, *,
                 record_rate_hz: float, position_pct=None, models=range(MAX_M + 1), selection: str = "ar1",
                 manoeuvre: str = "auto", tau_min_s=None, tau_max_s=None, friction=None, friction_unsteady=None,
                 progress=None) -> SectionsResult:
    """Calibrate one wall on every section of one record. ``heads``: transducer name -> absolute head on
    ``t_s`` (one per ``rig.sections``, named as in the rig; one at the valve, whose head drives the valve's
    orifice law); the rest as ``velab.fitting.prepare.fit_record``. DataError (one line) for a missing or
    unknown section, a rig without a transducer at the valve, or what fit_record refuses."""
    t0 = time.perf_counter()
    if selection not in SELECTIONS:
        raise DataError(f"unknown model selection {selection!r} (choose from {', '.join(SELECTIONS)})")
    sections = rig.sections
    names = [s.name for s in sections]
    missing = [n for n in names if n not in heads]
    unknown = [n for n in heads if n not in names]
    problems = ([f"no head for {', '.join(missing)}"] if missing else []) + \
        ([f"no transducer named {', '.join(unknown)} in the rig"] if unknown else [])
    if problems:
        raise DataError(f"sections: {'; '.join(problems)} (the rig's: {', '.join(names)})")
    L = rig.pipe.length_m
    at_valve = [s.name for s in sections if s.position_m == L]
    if not at_valve:
        raise DataError(f"sections: the rig has no transducer at the valve (position_m = {L:g}); its head "
                        f"drives the valve's flow")
    ms = parse_models(list(models) if isinstance(models, range) else models)
    frig = fit_rig(rig, friction, friction_unsteady)
    recs = {}
    for s in sections:
        try:
            recs[s.name] = prepare_record(t_s, heads[s.name], trigger_time_s, frig, window_s,
                                          record_rate_hz=record_rate_hz, position_pct=position_pct)
        except DataError as exc:
            raise DataError(f"section {s.name}: {exc}") from None
    valve_rec = recs[at_valve[0]]
    t = valve_rec.t
    vi = valve_input(t, valve_rec.h, frig, valve_rec.window_s, position_pct=valve_rec.position, mode=manoeuvre)
    shared = _SharedTime(frig, t, vi.flow, [s.position_m for s in sections])
    runs = [_SectionRun(s.name, s.position_m, recs[s.name], frig, vi, shared, i) for i, s in enumerate(sections)]
    valve_run = runs[names.index(at_valve[0])]
    bounds = derive_bounds(frig, float(t[1] - t[0]), valve_rec.window_s, tau_min_s=tau_min_s, tau_max_s=tau_max_s)
    sw = _JointSweep(runs, bounds, selection, progress)
    sw.sweep(ms, progress)
    # the fitted closure refined on the valve's whole window with the best wall, then every model continued
    for _ in range(REFINE_PASSES if vi.source == "fitted" else 0):
        first = _first_pass_best(sw, ms)
        pm = first.sol.pm
        a, J, tau = pm.unpack(first.sol.x)
        E = creep_const(frig) * a * a / np.asarray(J)
        wall = ModelFit(name=model_name(pm.m), m=pm.m, k=pm.size, reduced=False, n=valve_run.n, F=math.nan,
                        wave_speed_m_s=a, E_pa=tuple(E), eta_pa_s=tuple(E * tau), lag1_autocorr=0.0)
        vi = refine_closure(t, valve_rec.h, frig, vi, wall, bounds)
        shared.set_flow(vi.flow)
        for r in runs:
            r.set_flow(vi)
            r.set_friction((a, J, tau))
        for m in range(0, max(ms) + 1):
            sw.final[m] = sw.continue_model(m, sw.final[m])
    top = min(sw.final.values(), key=lambda f: f.loglik(runs))
    sw.reweight(top)
    p_top = top.sol.pm.unpack(top.sol.x)
    rows = [_closure_rows(r, valve_rec.h, vi, p_top) for r in runs]
    fits = [_summarise(sw, m, sw.final[m], vi.k, rows) for m in ms]
    apply_criteria(fits, selection)
    result = SectionsResult(n=fits[0].n, window_s=valve_rec.window_s, sample_rate_hz=valve_rec.fit_rate_hz,
                            method="sections", settings={}, models=fits, selection=selection)
    best = result.best
    result.sections, result.warnings = _per_section(runs, sw.final[best.m], best)
    result.settings = {"models": ms, "selection": selection, "sections": True, "bounds": bounds.to_dict(),
                       "manoeuvre": vi.describe(), "k_nuisance": vi.k,
                       "likelihood": "sum over sections of n_s ln F_s (each section's variance its own)",
                       "friction": {"steady": shared.tm.steady, "unsteady": shared.tm.unsteady,
                                    "time_domain": shared.tm.active}}
    result.record_rate_hz = valve_rec.record_rate_hz
    result.anti_alias_filter = valve_rec.filter
    if all(r.noise_var for r in runs):
        # pooled as F is (n-weighted geometric mean), so that a model's noise_ratio is F / noise^2
        result.baseline_noise_m = math.exp(sum(r.n * math.log(r.noise_var) for r in runs) / (2 * result.n))
        result.baseline_lag1 = float(np.average([r.rec.baseline_lag1 for r in runs], weights=[r.n for r in runs]))
    result.adequacy = {"baseline_samples": int(sum(r.rec.baseline_samples for r in runs)), "misfit_bound": None,
                       "per_section": "the misfit rule is applied to each section (sections[].misfit_bound, "
                                      "sections[].disagrees)"}
    if best.at_bounds:
        result.warnings.append({"code": "bound", "message": bound_message(best)})
    result.notes.append(f"fit of {len(runs)} sections ({', '.join(f'{r.name} at {r.position_m:g} m' for r in runs)}): "
                        f"one wall, one flow at the valve ({vi.source}), each section's noise its own")
    result.duration_s = time.perf_counter() - t0
    result.evaluations = 0
    return result


def run_heads(run) -> dict:
    """Each transducer's absolute head of a run read back from its file (velab.runfiles.reader.Run), by name:
    the channel ``rig.section_channel`` names (``head`` for the valve's, ``head_NAME`` for the others).
    DataError (one line, naming the file and the channel) for a transducer the file has no channel of."""
    rig = run.rig
    out = {}
    for sec in rig.sections:
        ch = rig.section_channel(sec)
        h = run.head_m if ch == "head" else run.channels.get(ch)
        if h is None:
            raise DataError(f"{run.path}: no channel {ch!r} for the transducer {sec.name!r} of its rig "
                            f"(channels: head, {', '.join(sorted(run.channels))})")
        out[sec.name] = h
    return out


# the single sweep's search options (velab.fitting.sweep.fit_sweep): the sections' fit is the joint sweep's
SWEEP_ONLY = {"method": "auto", "reduced": False, "starts": None, "polish": True}


def fit_run_sections(run, window_s: float | None, **options) -> SectionsResult:
    """:func:`fit_sections` on a run read back from its file, every transducer of its rig (velab.fitting.prepare
    .fit_run calls it for a rig with several). The single sweep's search options (``SWEEP_ONLY``) are accepted
    at their defaults; another value is one line (DataError): this fit searches as a joint fit does."""
    for key, default in SWEEP_ONLY.items():
        value = options.pop(key, default)
        if value != default and not (key == "starts" and value is None):
            raise DataError(f"{run.path}: {key} = {value!r}: not for a fit of several sections (its rig has "
                            f"{len(run.rig.sections)} transducers; the search is the joint fit's)")
    run.fit_window(window_s)  # the reader's own checks of the window (gaps, NaN), with the file's name
    return fit_sections(run.time_s, run_heads(run), run.trigger_time_s, run.rig, window_s,
                        record_rate_hz=run.sample_rate_hz, position_pct=run.channels.get("valve_position"), **options)


def _closure_rows(run: _SectionRun, d_valve, vi, params) -> np.ndarray:
    """d h_x / d v of the fitted closure's parameters not on a bound, at this section (the closure drives
    every section; velab.fitting.nuisance at x). Empty if not fitted."""
    models = closure_models(run.rig, run.rec.t, d_valve, vi, position_m=run.position_m)
    return rows_at(models, run.ev_f, params) if models else np.zeros((0, run.rec.t.size))


def _summarise(sw: _JointSweep, m: int, fin, k_nuisance: int, rows: list) -> ModelFit:
    """The joint sweep's summary, its wall's covariance marginalised over the ONE closure all sections share
    (its columns on every section's rows: one block, not one per section)."""
    f = sw.summarise(m, fin, k_nuisance, None)
    if not any(r.size for r in rows) or f.cov_x is None:
        return f
    saved = [r.var for r in sw.runs]
    for r, F in zip(sw.runs, fin.F_runs):
        r.var = float(F)
    st = sw.stage("f", fin)
    for r, v in zip(sw.runs, saved):
        r.var = v
    pm = fin.sol.pm
    h, jac = st.ev.head_jac_x(*pm.unpack(fin.sol.x), pm.tau_free)
    res = h - st.d
    block = np.concatenate([w * b for w, b in zip(st.ev.weights, rows)], axis=1)
    g = marginalised(f, pm, fin.sol.x, jac, [block], [slice(None)], [1.0], sumsq(res) / res.size, lag1(res),
                     sw.runs[0].rig)
    return g


def _per_section(runs, fin, best: ModelFit):
    """Per section: n, F and noise ratio under the fitted wall, and the single fit's misfit rule on it (a
    transducer whose position or calibration is wrong is named)."""
    out, warnings = [], []
    for i, r in enumerate(runs):
        sr = assess_part(best, r, fin.heads[i], float(fin.F_runs[i]), "sections")
        for w in sr.warnings:
            warnings.append({"code": w["code"], "message": f"section {r.name} ({r.position_m:g} m): {w['message']}",
                             "section": r.name})
        out.append({"name": r.name, "position_m": r.position_m, "n": r.n, "F": float(fin.F_runs[i]),
                    "noise_ratio": sr.models[0].noise_ratio, "baseline_noise_m": r.rec.baseline_noise_m,
                    "steady_head_m": r.rec.steady_head_m, "misfit_bound": sr.adequacy.get("misfit_bound"),
                    "disagrees": any(w["code"] == "misfit" for w in sr.warnings)})
    return out, warnings
