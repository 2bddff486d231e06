"""Joint calibration of one pipe over several runs (a campaign; physics.md section 12, issue 25 part 1).

One wall -- the wave speed a and the Kelvin-Voigt elements (J'_k, tau_k) -- is shared by every run;
each run keeps what is its own: steady state and friction at its Q0 (its rig), the flow at the valve
(its recorded position, or its closure fitted as nuisance parameters), noise level, sample rate.

Likelihood. Each run r is Gaussian with its own unknown variance sigma_r^2; profiled out
(sigma_r^2 = F_r = RSS_r / n_r), -2 ln L = sum_r n_r ln F_r + const: a single fit's n ln F summed
over runs. Its stationary point is the weighted least squares with weights 1/F_r, so the wall is
solved as weighted least squares over the stacked runs, weights 1 / (the run's baseline noise
variance) first (what a correct model leaves), then 1/F_r (the profile's fixed point): a run the
wall does not describe weighs by its own large residual and cannot drag the others. AIC =
sum_r n_r ln F_r + 2 k, k = the wall's 2m + 1 plus every run's nuisance parameters (the same for
every model: dAIC is the wall's). The pooled F reported is exp(sum_r n_r ln F_r / N), so that
N ln F is the likelihood term and velab.fitting.results.apply_criteria ranks as for one run.

Cost. Each run's nuisance (closure) is fitted once on its early window, which the wall barely moves
(velab.fitting.manoeuvre.valve_input); then every model's wall is searched on the runs' coarse
grids stacked (one Jacobian, rows of every run: the per-run HeadEvaluator reused through
``StackedEvaluator``), polished on grids at 8 x the manoeuvre's band, with each run's time-domain
(friction) head as a defect correction refreshed at the optimum, and summarised at the fit rate.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, replace

import numpy as np

from velab.errors import DataError
from velab.fitting.adequacy import assess, bound_message
from velab.fitting.campaignrun import CampaignRun, check_same_pipe
from velab.fitting.creep import creep_curve
from velab.fitting.data import lowpass_decimate
from velab.fitting.engine import HeadEvaluator, sumsq
from velab.fitting.friction import TimeDomainModel, equivalent_friction, fit_rig
from velab.fitting.manoeuvre import valve_input
from velab.fitting.nuisance import closure_rows, marginalised
from velab.fitting.parallel import map_pair
from velab.fitting.jointresult import JointResult
from velab.fitting.params import ParamMap, creep_const, derive_bounds
from velab.fitting.prepare import PreparedRecord, prepare_record
from velab.fitting.refine import refine_closure
from velab.fitting.results import SELECTIONS, ModelFit, SweepResult, apply_criteria, model_name
from velab.fitting.solvers import Sol, Stage
from velab.fitting.starts import nested_starts, race_starts, reduced_then_full, scan_wave_speed, tau_grids
from velab.fitting.stacked import StackedEvaluator
from velab.fitting.stats import ar1_innovation_var, lag1
from velab.fitting.summary import summarise
from velab.fitting.sweep import MAX_M, SATURATED_GAIN, parse_models
from velab.model import manoeuvre_band_hz

POLISH_RATE_PER_BAND = 8.0  # the polish runs on each run's record decimated to this multiple of its band
REFRESHES = 3  # time-domain (friction) refreshes of each model's optimum, at most
REFRESH_GAIN = 0.05
# closure refinements (each run's, with the joint wall) followed by a continuation of every model; a
# second pass was measured to change nothing that matters (J(0.05 s) moved 0.1 %, a 0.003 m/s) for 1.5 x the time
REFINE_PASSES = 1  # ... stopped when one gains less than this in sum n ln F


def per_run(fn, items: list) -> list:
    """[fn(item) for item in items], shared out over two threads on a machine with two cores or more: each
    run's own work (closure fits, time-domain heads) touches only that run's objects, and the results do
    not depend on which thread ran which (velab.fitting.parallel.map_pair)."""
    return map_pair(lambda _, item: fn(item), items, lambda: None, parallel=(os.cpu_count() or 1) > 1)


class _Run:
    """One run's own part of a joint fit: its prepared record, flow at the valve, models on three
    grids (coarse search, polish, fit rate), time-domain model and weight."""

    def __init__(self, src: CampaignRun, window_s: float | None, manoeuvre: str, friction, friction_unsteady):
        self.src = src
        self.rig = fit_rig(src.rig, friction, friction_unsteady)
        self.rec: PreparedRecord = prepare_record(src.time_s, src.head_m, src.trigger_time_s, self.rig, window_s,
                                                  record_rate_hz=src.record_rate_hz, position_pct=src.position_pct)
        t, d = self.rec.t, self.rec.h
        # the run's nuisance parameters: its closure, fitted on the early window (wall-insensitive)
        self.vi = valve_input(t, d, self.rig, self.rec.window_s, position_pct=self.rec.position, mode=manoeuvre)
        flow = self.vi.flow
        fs = 1.0 / float(t[1] - t[0])
        band = manoeuvre_band_hz(self.rig)
        self.qc = max(1, int(fs // (3.0 * band)))  # as the single sweep's coarse stage
        self.qm = max(1, int(fs // (POLISH_RATE_PER_BAND * band)))
        self.ev_c = HeadEvaluator(self.rig, t[:: self.qc], band_hz="auto", flow=flow[:: self.qc])
        self.ev_m = HeadEvaluator(self.rig, t[:: self.qm], band_hz=None, flow=flow[:: self.qm])
        self.ev_f = HeadEvaluator(self.rig, t, band_hz=None, flow=flow)
        self.tm = TimeDomainModel(self.rig, t, flow=flow)
        self.noise_var = self.rec.baseline_noise_m ** 2 if self.rec.baseline_noise_m else None
        self.var = self.noise_var  # the weight's variance: the baseline's, then the run's own F

    @property
    def n(self) -> int:
        return int(self.rec.h.size)

    def set_flow(self, vi) -> None:
        """The run's models driven by another flow at the valve (a refined closure)."""
        self.vi = vi
        t, flow = self.rec.t, vi.flow
        self.ev_c = HeadEvaluator(self.rig, t[:: self.qc], band_hz="auto", flow=flow[:: self.qc])
        self.ev_m = HeadEvaluator(self.rig, t[:: self.qm], band_hz=None, flow=flow[:: self.qm])
        self.ev_f = HeadEvaluator(self.rig, t, band_hz=None, flow=flow)
        self.tm = TimeDomainModel(self.rig, t, flow=flow)

    def refine(self, fin: "_Model", bounds) -> None:
        """The fitted closure refined on the whole window with the joint wall ``fin`` as the start
        (velab.fitting.refine.refine_closure: this run's wall is free there, only the closure is kept)."""
        if self.vi.source != "fitted":
            return
        pm = fin.sol.pm
        a, J, tau = pm.unpack(fin.sol.x)
        c = creep_const(self.rig)
        wall = ModelFit(name=model_name(pm.m), m=pm.m, k=pm.size, reduced=False, n=self.n, F=math.nan,
                        wave_speed_m_s=a, E_pa=tuple(c * a * a / np.asarray(J)), eta_pa_s=tuple(c * a * a / np.asarray(J) * tau),
                        lag1_autocorr=0.0)
        self.set_flow(refine_closure(self.rec.t, self.rec.h, self.rig, self.vi, wall, bounds))

    def set_friction(self, params) -> None:
        """The linear friction closest to this run's time-domain head at ``params`` (only how fast the
        defect correction converges, not where: the fitted head is the time-domain model's)."""
        if not self.tm.active:
            return
        h_time = self.tm.head(*params)
        eq = equivalent_friction(self.ev_c, params, lowpass_decimate(h_time, self.qc))
        self.ev_c, self.ev_m, self.ev_f = self.ev_c.fork(eq), self.ev_m.fork(eq), self.ev_f.fork(eq)

    def model_head(self, params) -> np.ndarray:
        """The head of the run's model at the fit rate: the time-domain model's with a nonlinear friction."""
        return self.tm.head(*params) if self.tm.active else self.ev_f.head(*params)


@dataclass
class _Model:
    """A calibrated wall and each run's model head at it (the time-domain model's: the F compared)."""

    sol: Sol
    heads: list
    F_runs: np.ndarray

    def loglik(self, runs) -> float:
        """sum_r n_r ln F_r (-2 ln L up to a constant)."""
        return float(sum(r.n * math.log(F) for r, F in zip(runs, self.F_runs)))


def assess_part(best: ModelFit, part, head, F: float, method: str) -> SweepResult:
    """The single fit's adequacy (velab.fitting.adequacy.assess: noise ratio, misfit rule) on one part of a
    stacked fit -- a run of a campaign, a section of a record -- under the shared wall: ``part`` has
    ``n``, ``rec`` (its PreparedRecord) and ``rig``; ``head`` its model head, ``F`` its mean square."""
    one = replace(best, n=part.n, F=F, lag1_autocorr=lag1(head - part.rec.h), at_bounds=[])
    sr = SweepResult(n=part.n, window_s=part.rec.window_s, sample_rate_hz=part.rec.fit_rate_hz, method=method,
                     settings={}, models=[one])
    assess(sr, part.rec, part.rig)
    return sr


class _JointSweep:
    def __init__(self, runs: list[_Run], bounds, selection: str, progress=None):
        self.runs, self.bounds, self.selection, self.progress = runs, bounds, selection, progress
        self.final: dict[int, _Model] = {}
        self.not_searched: list[int] = []
        dt = min(float(r.rec.t[1] - r.rec.t[0]) * r.qc for r in runs)
        window = max(r.rec.window_s for r in runs)
        self.tau_lo = max(2 * dt, bounds.tau_min_s)
        self.tau_hi = min(max(window / 2.0, 4 * self.tau_lo), bounds.tau_max_s)

    # ------------------------------------------------------------ stages
    def weights(self) -> np.ndarray:
        # a run without a usable baseline (too short) starts at the others' typical variance until its own
        # F replaces it (after the first model's polish)
        known = [r.var for r in self.runs if r.var]
        fallback = float(np.median(known)) if known else 1.0
        return np.array([1.0 / math.sqrt(r.var or fallback) for r in self.runs])

    def stage(self, grid: str, base: _Model | None) -> Stage:
        """The stacked stage on ``grid`` ("c", "m", "f"), its data defect-corrected at ``base``: each run's
        data minus its time-domain head at ``base`` plus its frequency model there (the frequency model
        then fits the time-domain model's head near ``base``)."""
        evs, parts = [], []
        for i, r in enumerate(self.runs):
            ev, q = {"c": (r.ev_c, r.qc), "m": (r.ev_m, r.qm), "f": (r.ev_f, 1)}[grid]
            evs.append(ev)
            if base is None or not r.tm.active:
                parts.append(lowpass_decimate(r.rec.h, q) if q > 1 else r.rec.h)
            else:
                p = base.sol.pm.unpack(base.sol.x)
                dcorr = r.rec.h - base.heads[i]
                parts.append((lowpass_decimate(dcorr, q) if q > 1 else dcorr) + ev.head(*p))
        st = StackedEvaluator(evs, self.weights())
        return Stage(st, st.stack(parts))

    def evaluate(self, sol: Sol) -> _Model:
        """Each run's model head at ``sol`` (time-domain with a nonlinear friction) and its F."""
        p = sol.pm.unpack(sol.x)
        heads = per_run(lambda r: r.model_head(p), self.runs)
        F = np.array([sumsq(h - r.rec.h) / r.n for h, r in zip(heads, self.runs)])
        return _Model(sol, heads, F)

    # ------------------------------------------------------------ models
    def sweep(self, ms: list[int], progress=None) -> None:
        """EL, S1, ... up to the largest of ``ms``, each from the one before (``final``);
        ``progress(done, total, name)`` after each model of ``ms``."""
        base = self.start()
        for m in range(0, max(ms) + 1):
            fin = base if m == 0 else self.fit_model(m, base)
            if m == 0:
                fin = self.polish(ParamMap(0, self.bounds), base.sol.x, base)
            self.final[m] = fin
            base = fin
            if progress is not None and m in ms:
                progress(ms.index(m) + 1, len(ms), model_name(m))

    def start(self) -> _Model:
        pm0 = ParamMap(0, self.bounds)
        a_nom = self.runs[0].rig.nominal_wave_speed_m_s
        for r in self.runs:
            r.set_friction((a_nom, [], []))
        a0 = scan_wave_speed(self.stage("c", None), pm0, a_nom)
        return self.evaluate(Sol(pm0.pack(a0, []), math.nan, pm0))

    def fit_model(self, m: int, base: _Model) -> _Model:
        pm = ParamMap(m, self.bounds)
        ref = self.final.get(m - 1)
        if ref is not None and m >= 4 and self.saturated(m):
            self.not_searched.append(m)
            return self.embedded(pm, ref)
        if m in (1, 3) and self.runs[0].tm.active:  # the linear stand-in of the friction near this wall
            for r in self.runs:
                r.set_friction(base.sol.pm.unpack(base.sol.x))
        coarse = self.stage("c", base)
        a_base = base.sol.pm.unpack(base.sol.x)[0]
        cands = nested_starts(base.sol, pm, self.bounds, self.tau_lo, self.tau_hi)[:-1] if base.sol.pm.m else []
        if m <= 3 and not (m == 3 and self.saturated(m)):
            cands += [reduced_then_full(coarse, pm, g, a_base, "auto") for g in tau_grids(m, self.tau_lo, self.tau_hi)]
        sols = race_starts(coarse, pm, cands, 60)
        sols.sort(key=lambda s: s.F)
        x = coarse.lsq(pm, sols[0].x, max_nfev=150, ftol=1e-12).x
        fin = self.polish(pm, x, base)
        if ref is not None and fin.loglik(self.runs) > ref.loglik(self.runs):
            # the nesting guard: S(m) contains S(m-1) (an element can vanish)
            emb = self.polish(pm, pm.embed(ref.sol.pm, ref.sol.x), ref)
            fin = min((fin, emb, self.embedded(pm, ref)), key=lambda f: f.loglik(self.runs))
        return fin

    def polish(self, pm: ParamMap, x, base: _Model, first_nfev: int = 40) -> _Model:
        """Polish on the stacked polish grids with the time-domain correction at ``base``, refreshed at the
        optimum, and the runs' weights moved to their own F there (the profile likelihood's fixed point:
        iteratively reweighted least squares), until sum n_r ln F_r stops moving."""
        best = None
        cur = base
        for it in range(REFRESHES):
            st = self.stage("m", cur)
            x = st.lsq(pm, x, max_nfev=first_nfev if it == 0 else 20, ftol=1e-10).x
            cur = self.evaluate(Sol(pm.project(x), math.nan, pm))
            gain = best.loglik(self.runs) - cur.loglik(self.runs) if best is not None else math.inf
            if gain > 0:
                best = cur
                self.reweight(cur)
            if gain < REFRESH_GAIN:
                break
        return best

    def continue_model(self, m: int, old: _Model) -> _Model:
        """After the runs' closures were refined: the model polished from its previous optimum (no search),
        not above the model it contains."""
        pm = old.sol.pm
        if m in self.not_searched:
            return self.embedded(pm, self.final[m - 1])
        start = self.evaluate(old.sol)
        fin = self.polish(pm, old.sol.x, start, first_nfev=25)
        if start.loglik(self.runs) < fin.loglik(self.runs):
            fin = start  # (a polish accepts only steps that lower its objective, whose weights moved)
        ref = self.final.get(m - 1)
        if ref is not None and fin.loglik(self.runs) > ref.loglik(self.runs):
            fin = self.embedded(pm, ref)
        return fin

    def embedded(self, pm: ParamMap, ref: _Model) -> _Model:
        return _Model(Sol(pm.embed(ref.sol.pm, ref.sol.x), ref.sol.F, pm), ref.heads, ref.F_runs)

    def saturated(self, m: int) -> bool:
        f1, f2 = self.final.get(m - 1), self.final.get(m - 2)
        if f1 is None or f2 is None:
            return False
        return f2.loglik(self.runs) - f1.loglik(self.runs) < SATURATED_GAIN

    def reweight(self, model: _Model) -> None:
        for r, F in zip(self.runs, model.F_runs):
            r.var = float(F)

    # ------------------------------------------------------------ summary
    def summarise(self, m: int, fin: _Model, k_nuisance: int, nuisance=None) -> ModelFit:
        """The ModelFit of the joint wall: standard errors from the stacked weighted Jacobian at the fit
        rate (weights 1/F_r; inflated for the residuals' lag-1 as for one run), marginalised over the runs'
        fitted closures (``nuisance``: each run's closure rows, velab.fitting.nuisance); F, AIC over the runs."""
        saved = [r.var for r in self.runs]
        for r, F in zip(self.runs, fin.F_runs):
            r.var = float(F)
        st = self.stage("f", fin)
        f = summarise(st, fin.sol, model_name(m), self.runs[0].rig, self.bounds,
                      evaluations=st.ev.evaluations, jacobians=st.ev.jacobians)
        n_tot = sum(r.n for r in self.runs)
        if nuisance is not None and any(b.size for b in nuisance):
            h, jac = st.ev.head_jac_x(*fin.sol.pm.unpack(fin.sol.x), fin.sol.pm.tau_free)
            res = h - st.d
            f = marginalised(f, fin.sol.pm, fin.sol.x, jac, nuisance, st.ev.slices(), st.ev.weights,
                             sumsq(res) / res.size, lag1(res), self.runs[0].rig)
        for r, v in zip(self.runs, saved):
            r.var = v
        # per run: its residual's lag-1 and AR(1) innovation variance; pooled so that apply_criteria's
        # N ln s_e^2 - ln(1 - rho^2) is the sum of the runs' AR(1) terms
        ar, rhos = 0.0, []
        for r, h in zip(self.runs, fin.heads):
            res = h - r.rec.h
            rho = lag1(res)
            rhos.append(rho)
            rho_c = float(np.clip(rho, -0.999, 0.999))
            ar += r.n * math.log(ar1_innovation_var(res, rho)) - math.log(1 - rho_c * rho_c)
        rho_p = float(np.clip(np.average(rhos, weights=[r.n for r in self.runs]), -0.999, 0.999))
        F = math.exp(fin.loglik(self.runs) / n_tot)
        ratio = None
        if all(r.noise_var for r in self.runs):
            ratio = math.exp(sum(r.n * math.log(F_r / r.noise_var) for r, F_r in zip(self.runs, fin.F_runs)) / n_tot)
        return replace(f, n=n_tot, F=F, k=f.k + k_nuisance, lag1_autocorr=rho_p,
                       innovation_var=math.exp((ar + math.log(1 - rho_p * rho_p)) / n_tot), noise_ratio=ratio)


def fit_joint(sources: list[CampaignRun], window_s: float | None = 20.0, *, models=range(MAX_M + 1),
              selection: str = "ar1", manoeuvre: str = "auto", tau_min_s=None, tau_max_s=None, friction=None,
              friction_unsteady=None, progress=None) -> JointResult:
    """Calibrate one wall on several runs of one pipe (see the module docstring). ``sources``: the runs
    (``CampaignRun``), two or more; the other options as ``fit_record``. Raises DataError (one line,
    naming the run) for runs of different pipes, a window a run does not hold, bad options."""
    if len(sources) < 2:
        raise DataError("a joint fit needs two or more runs")
    if selection not in SELECTIONS:
        raise DataError(f"unknown model selection {selection!r} (choose from {', '.join(SELECTIONS)})")
    check_same_pipe(sources)
    t0 = time.perf_counter()
    ms = parse_models(list(models) if isinstance(models, range) else models)

    def make(s):
        try:
            return _Run(s, window_s, manoeuvre, friction, friction_unsteady)
        except DataError as exc:
            raise DataError(f"{s.path}: {exc}") from None

    runs = per_run(make, sources)
    dt = min(float(r.rec.t[1] - r.rec.t[0]) for r in runs)
    bounds = derive_bounds(runs[0].rig, dt, max(r.rec.window_s for r in runs), tau_min_s=tau_min_s,
                           tau_max_s=tau_max_s)
    sw = _JointSweep(runs, bounds, selection, progress)
    sw.sweep(ms, progress)
    # the fitted closures refined on each run's whole window with the best wall (every wave front carries
    # the closure's shape; from its early window alone a slow element takes up a wrong shape), then every
    # model continued from its optimum under them
    for _ in range(REFINE_PASSES if any(r.vi.source == "fitted" for r in runs) else 0):
        first = _first_pass_best(sw, ms)
        p = first.sol.pm.unpack(first.sol.x)

        def refine(r, first=first, p=p):
            r.refine(first, sw.bounds)
            r.set_friction(p)

        per_run(refine, runs)
        for m in range(0, max(ms) + 1):
            sw.final[m] = sw.continue_model(m, sw.final[m])
    top = min(sw.final.values(), key=lambda f: f.loglik(runs))
    sw.reweight(top)
    k_nuis = sum(r.vi.k for r in runs)
    # the closures' columns at the best-fitting wall, for the wall's covariance marginalised over them
    p_top = top.sol.pm.unpack(top.sol.x)
    nuisance = per_run(lambda r: closure_rows(r.rig, r.rec.t, r.rec.h, r.ev_f, r.vi, p_top), runs)
    fits = [sw.summarise(m, sw.final[m], k_nuis, nuisance) for m in ms]
    apply_criteria(fits, selection)
    result = JointResult(n=fits[0].n, window_s=max(r.rec.window_s for r in runs),
                         sample_rate_hz=min(r.rec.fit_rate_hz for r in runs), method="joint", settings={},
                         models=fits, selection=selection)
    best = result.best
    result.settings = _settings(runs, ms, bounds, selection, sw, k_nuis, tau_min_s, tau_max_s)
    result.runs, result.warnings = _per_run(runs, sw, sw.final[best.m], best, bounds)
    if all(r["disagrees"] for r in result.runs):
        # every run beyond its noise: the model (or the rig files), not one run, does not describe them
        result.warnings.insert(0, {"code": "misfit", "message": f"the best model {best.name} leaves residuals above "
                                   f"the noise in every run: its wall is not the pipe's; check the rig files, the "
                                   f"valve, air, friction, and the models fitted"})
    result.record_rate_hz = max(r.rec.record_rate_hz for r in runs)
    result.anti_alias_filter = "per run (runs[].anti_alias_filter)"
    if all(r.noise_var for r in runs):
        # pooled as F is (n-weighted geometric mean), so that a model's noise_ratio is F / noise^2
        result.baseline_noise_m = math.exp(sum(r.n * math.log(r.noise_var) for r in runs) / (2 * result.n))
        result.baseline_lag1 = float(np.average([r.rec.baseline_lag1 for r in runs], weights=[r.n for r in runs]))
    result.adequacy = {"baseline_samples": int(sum(r.rec.baseline_samples for r in runs)), "misfit_bound": None,
                       "per_run": "the misfit rule is applied to each run (runs[].misfit_bound, runs[].disagrees)"}
    if best.at_bounds:
        result.warnings.append({"code": "bound", "message": bound_message(best)})
    result.notes.append(f"joint fit of {len(runs)} runs: one wall (a, J_k, tau_k) shared; per run its own steady state, "
                        f"friction at its Q0, flow at the valve ({k_nuis} nuisance parameters in all, counted in k) "
                        f"and noise; -2 ln L = sum over runs of n_r ln F_r (each run's variance its own)")
    if sw.not_searched:
        result.notes.append(", ".join(model_name(m) for m in sw.not_searched)
                            + ": not searched, the model below plus vanished elements (its element did not pay "
                              "its AIC price)")
    result.duration_s = time.perf_counter() - t0
    result.evaluations = 0
    return result


def _first_pass_best(sw: _JointSweep, ms) -> _Model:
    """The model of the first pass with the least white AIC (sum n_r ln F_r + 2 (2m + 1))."""
    return min((sw.final[m] for m in ms), key=lambda f: f.loglik(sw.runs) + 2 * f.sol.pm.size)


def _settings(runs, ms, bounds, selection, sw, k_nuis, tau_min_s, tau_max_s) -> dict:
    return {"models": ms, "reduced": False, "polish": True, "selection": selection, "joint": True,
            "bounds": bounds.to_dict(), "tau_min_s": tau_min_s, "tau_max_s": tau_max_s,
            "tau_start_range_s": [sw.tau_lo, sw.tau_hi], "not_searched": [model_name(m) for m in sw.not_searched],
            "k_shared": "2m + 1", "k_nuisance": k_nuis,
            "likelihood": "sum over runs of n_r ln F_r (Gaussian, each run's own variance profiled out)",
            "friction": {"steady": runs[0].tm.steady, "unsteady": runs[0].tm.unsteady,
                         "time_domain": runs[0].tm.active,
                         "text": "each run's head is its time-domain model (its own Q0) at the wall, fitted through "
                                 "its frequency model plus a correction refreshed at the optimum"
                                 if runs[0].tm.active else runs[0].tm.describe()}}


def _per_run(runs, sw: _JointSweep, fin: _Model, best: ModelFit, bounds):
    """Per run: its F and noise ratio under the joint wall, whether it disagrees (the single fit's misfit
    rule on that run: velab.fitting.adequacy.assess), and its own wall under the best model (a polish
    from the joint wall on that run alone) for the campaign figure."""
    out, warnings = [], []
    owns = per_run(lambda i: _own_wall(sw, i, fin, best.m, bounds), list(range(len(runs))))
    for i, r in enumerate(runs):
        sr = assess_part(best, r, fin.heads[i], float(fin.F_runs[i]), "joint")
        for w in sr.warnings:
            warnings.append({"code": w["code"], "message": f"{r.src.path}: {w['message']}", "run": r.src.path})
        own = owns[i]
        out.append({
            "path": r.src.path, "head_sha256": r.src.head_sha256, "n": r.n, "window": r.rec.window_s,
            "sample_rate_hz": r.rec.fit_rate_hz, "record_rate_hz": r.rec.record_rate_hz,
            "anti_alias_filter": r.rec.filter, "steady_flow_m3_s": r.rig.steady_flow_m3_s,
            "steady_head_m": r.rec.steady_head_m, "F": float(fin.F_runs[i]), "noise_ratio": sr.models[0].noise_ratio,
            "baseline_noise_m": r.rec.baseline_noise_m, "misfit_bound": sr.adequacy.get("misfit_bound"),
            "disagrees": any(w["code"] == "misfit" for w in sr.warnings),
            "warnings": [w["code"] for w in sr.warnings],
            "manoeuvre": r.vi.describe(),
            "own": {"model": best.name, "wave_speed": own.wave_speed_m_s, "wave_speed_se": own.wave_speed_se_m_s,
                    "F": own.F, "elements": own.elements(), "cov_x": own.cov_x,
                    "creep": creep_curve(own, t_min_s=bounds.tau_min_s, t_max_s=r.rec.window_s).to_dict()},
        })
    return out, warnings


def _own_wall(sw: _JointSweep, i: int, fin: _Model, m: int, bounds) -> ModelFit:
    """The best model's wall fitted on run i alone, from the joint wall (polish grid, time-domain correction
    at the joint wall, one refresh), summarised at the fit rate."""
    r = sw.runs[i]
    pm = fin.sol.pm
    x = fin.sol.x
    heads = fin.heads[i]
    for _ in range(2):
        p = pm.unpack(x)
        dcorr = r.rec.h - heads
        data = (lowpass_decimate(dcorr, r.qm) if r.qm > 1 else dcorr) + r.ev_m.head(*p) if r.tm.active else \
            (lowpass_decimate(r.rec.h, r.qm) if r.qm > 1 else r.rec.h)
        x = Stage(r.ev_m, data).lsq(pm, x, max_nfev=30, ftol=1e-10).x
        heads = r.model_head(pm.unpack(x))
    p = pm.unpack(x)
    data = r.rec.h - heads + r.ev_f.head(*p) if r.tm.active else r.rec.h
    return summarise(Stage(r.ev_f, data), Sol(x, math.nan, pm), model_name(m), r.rig, bounds)
