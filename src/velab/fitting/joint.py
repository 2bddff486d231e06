"""Joint calibration of one pipe over several runs (a campaign; physics.md section 12, issue 25 parts 1 and 2).

One wall -- the wave speed a and the Kelvin-Voigt elements (J'_k, tau_k) -- is shared by every run;
each run keeps what is its own: steady state and friction at its Q0 (its rig), the flow at the valve
(its recorded position, or its closure fitted as nuisance parameters), noise level, sample rate. A run
whose rig has several transducers brings every section (velab.fitting.parts): each section is a part of
the stacked fit with its own noise and weight, the run's closure drives all of them and is counted once.

Likelihood. Each part r (a run's section) is Gaussian with its own unknown variance sigma_r^2; profiled
out (sigma_r^2 = F_r = RSS_r / n_r), -2 ln L = sum_r n_r ln F_r + const: a single fit's n ln F summed
over the parts. Its stationary point is the weighted least squares with weights 1/F_r, so the wall is
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
import time
from dataclasses import dataclass, replace

import numpy as np

from velab.config import REDUCED_RETARDATION_TIMES_S
from velab.errors import DataError
from velab.fitting.adequacy import assess, bound_message, model_error_message
from velab.fitting.campaignrun import CampaignRun, check_same_pipe
from velab.fitting.creep import creep_curve
from velab.fitting.data import lowpass_decimate
from velab.fitting.engine import sumsq
from velab.fitting.nuisance import marginalised
from velab.fitting.offset import counted_on, fitted, objective, offset, project
# (each run's own work, time-domain heads and closure refinements, touches only that run's objects: map_each)
from velab.fitting.parallel import map_each
from velab.fitting.jointresult import JointResult
from velab.fitting.params import ParamMap, derive_bounds
from velab.fitting.parts import Part, Record
# the single path's closure rules, one fact in one place: the stacked engine applies them too (refine_closures)
from velab.fitting.prepare import CLOSURE_ROUNDS, RIVAL_DAIC
from velab.fitting.results import ModelFit, SweepResult, model_name
from velab.fitting.selection import aic_ar1, aic_of, apply_criteria, pays, pooled_ar1
from velab.fitting.solvers import Sol, Stage
from velab.fitting.starts import (RACE_KEEP, cap_starts, coarse_search, continues_by_lsq, distinct, nested_starts,
                                  reduced_then_full, scan_wave_speed, tau_grids)
from velab.fitting.stacked import Count, StackedEvaluator
from velab.fitting.stackreduced import below, jobs, sweep_reduced
from velab.fitting.stats import ar1_innovation_var, lag1
from velab.fitting.summary import summarise
from velab.fitting.options import FitOptions

# time-domain (friction) refreshes of each model's optimum, at most; each polish stops at a refresh that gains less
# than REFRESH_GAIN in sum n ln F. Three had stopped S1 of tests/fitting/test_fit_truths.py's imperial S1 truth (the
# rig's flow) 10.7 short of its optimum, still gaining 1,900 at the third (the first correction is the model below's,
# far from this wall); S2 = S1 + a vanished element took those back and was named. Measured: 5 there, and on
# benchmarks/fit_joint.py's campaign S1 and S2 (far behind S3) still gaining 250 and 0.8 at the third
REFRESHES = 8
REFRESH_GAIN = 0.05
# closure refinements (each run's, with the joint wall) followed by a continuation of every model; a
# second pass was measured to change nothing that matters (J(0.05 s) moved 0.1 %, a 0.003 m/s) for 1.5 x the time
REFINE_PASSES = 1
# a model's basins are searched on this many parts, those the model below describes best (relative to their own
# noise): the wall is one, so a few runs find its basin; the search's best starts are then ranked and solved on
# every part (the search on all five runs of a campaign was a sixth of the joint fit)
SEARCH_PARTS = 2
# after the closures' refinement, a model whose white AIC (at its first-pass wall, under the refined closures) is
# behind the best's by more than this, or by more than this share of the samples if that is more, is not polished
# again: no polish closes such a gap (on benchmarks/fit_joint.py's five runs, 100,000 samples, polishing S1 and S2
# again gained 27 and 87, against gaps of 200,000 and 12,000), and their polishes were a third of the continuation
CONTINUE_MARGIN = 200.0
CONTINUE_MARGIN_PER_SAMPLE = 0.005


@dataclass
class _Model:
    """A calibrated wall and each run's model head at it (the time-domain model's: the F compared)."""

    sol: Sol
    heads: list
    F_runs: np.ndarray

    def loglik(self, runs) -> float:
        """sum_r n_r ln F_r (-2 ln L up to a constant)."""
        return float(sum(r.n * math.log(F) for r, F in zip(runs, self.F_runs)))

    def white_aic(self, runs) -> float:
        """sum_r n_r ln F_r + 2 (2m + 1): the wall's AIC with white residuals (the runs' nuisance is common)."""
        return aic_of(self.loglik(runs), self.sol.pm.size)


def baseline_blocks(parts, st: StackedEvaluator) -> tuple:
    """Each part's steady head offset fitted with the wall, its baseline the prior (velab.fitting.offset): the
    blocks (start, stop, n_b) of the stacked grid, each part's baseline counted on its grid there."""
    return tuple((sl.start, sl.stop, counted_on(p.steady_n, p.n, sl.stop - sl.start))
                 for p, sl in zip(parts, st.slices()))


def assess_part(best: ModelFit, part, head, F: float, method: str) -> SweepResult:
    """The single fit's adequacy (velab.fitting.adequacy.assess: noise ratio, misfit rule) on one part of a
    stacked fit -- a run of a campaign, a section of a record -- under the shared wall: ``part`` has
    ``n``, ``rec`` (its PreparedRecord) and ``rig``; ``head`` its model head, ``F`` its mean square."""
    one = replace(best, n=part.n, F=F, lag1_autocorr=lag1(fitted(head - part.rec.h, part.steady_n)), at_bounds=[])
    sr = SweepResult(n=part.n, window_s=part.rec.window_s, sample_rate_hz=part.rec.fit_rate_hz, method=method,
                     settings={}, models=[one])
    assess(sr, part.rec, part.rig)
    return sr


class StackedSweep:
    """The sweep over stacked parts (velab.fitting.parts.Part: a run's section; named ``runs`` here, as a joint
    fit of single-section runs has one part per run).

    The search (velab.fitting.options.FitOptions, as the single sweep's): ``method`` the coarse local solver
    (velab.fitting.starts.coarse_search; "least-squares": one start), ``starts`` at most this many coarse starts a
    model, ``seed`` the evolution's (plus m), ``polish`` False: each model's wall polished, refreshed and
    reweighted on the coarse grid, not the polish grid ("m"); ``reduced``: also S1r..S5r (tau fixed,
    velab.fitting.stackreduced). ``final`` is keyed (m, reduced), as the single sweep's jobs."""

    def __init__(self, runs: list[Part], bounds, selection: str, progress=None, *, method: str = "auto",
                 starts: int | None = None, seed: int = 0, polish: bool = True, reduced: bool = False):
        self.runs, self.bounds, self.selection, self.progress = runs, bounds, selection, progress
        self.method, self.seed, self.polish_full, self.reduced = method, seed, polish, reduced
        self.max_starts = 1 if method == "least-squares" else starts
        self.polish_grid = "m" if polish else "c"
        self.final: dict[tuple[int, bool], _Model] = {}
        self.not_searched: list[int] = []  # (full models only, as the single sweep's)
        # models (m, reduced) not polished after the closures' last refinement (refine_closures)
        self.not_continued: list[tuple[int, bool]] = []
        self.closure_notes: list[str] = []  # what the closures' rounds and the rival's comparison did (refine_closures)
        self.count = Count()  # the stacked model's evaluations over the whole sweep (the result's ``evaluations``)
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

    def stage(self, grid: str, base: _Model | None, idx=None) -> Stage:
        """The stacked stage on ``grid`` ("c", "m", "f"), its data defect-corrected at ``base``: each run's
        data minus its time-domain head at ``base`` plus its frequency model there (the frequency model
        then fits the time-domain model's head near ``base``). ``idx``: only these parts (all if None)."""
        idx = range(len(self.runs)) if idx is None else idx
        evs, parts = [], []
        for i in idx:
            r = self.runs[i]
            ev, q = {"c": (r.ev_c, r.qc), "m": (r.ev_m, r.qm), "f": (r.ev_f, 1)}[grid]
            evs.append(ev)
            if base is None or not r.tm.active:
                parts.append(lowpass_decimate(r.rec.h, q) if q > 1 else r.rec.h)
            else:
                p = base.sol.pm.unpack(base.sol.x)
                dcorr = r.rec.h - base.heads[i]
                parts.append((lowpass_decimate(dcorr, q) if q > 1 else dcorr) + ev.head(*p))
        st = StackedEvaluator(evs, self.weights()[list(idx)], self.count)
        return Stage(st, st.stack(parts), baseline_blocks([self.runs[i] for i in idx], st))

    def search_parts(self, base: _Model) -> list[int]:
        """The SEARCH_PARTS parts that ``base`` describes best, by F over their baseline's noise (a run that
        does not belong to the pipe is the worst described), in their order."""
        if len(self.runs) <= SEARCH_PARTS:
            return list(range(len(self.runs)))
        ratio = [F / (r.noise_var or F) for r, F in zip(self.runs, base.F_runs)]
        return sorted(np.argsort(ratio, kind="stable")[:SEARCH_PARTS].tolist())

    def evaluate(self, sol: Sol) -> _Model:
        """Each run's model head at ``sol`` (time-domain with a nonlinear friction) and its F."""
        p = sol.pm.unpack(sol.x)
        heads = map_each(lambda r: r.model_head(p), self.runs)
        F = np.array([objective(h - r.rec.h, r.steady_n) / r.n for h, r in zip(heads, self.runs)])
        return _Model(sol, heads, F)

    # ------------------------------------------------------------ models
    def jobs(self, ms) -> list[tuple[int, bool]]:
        """The models (m, reduced) a fit of ``ms`` reports, in fit_sweep's order (the full, then the reduced)."""
        return jobs(ms, self.reduced)

    def sweep(self, ms: list[int], progress=None) -> None:
        """EL, S1, ... up to the largest of ``ms``, each from the one before (``final``), then with ``reduced``
        S1r, ... (velab.fitting.stackreduced.sweep_reduced); ``progress(done, total, name)`` after each model
        reported (``jobs``)."""
        total = len(self.jobs(ms))
        base = self.start()
        for m in range(0, max(ms) + 1):
            fin = base if m == 0 else self.fit_model(m, base)
            if m == 0:
                fin = self.polish(ParamMap(0, self.bounds), base.sol.x, base)
            self.final[(m, False)] = fin
            base = fin
            if progress is not None and m in ms:
                progress(ms.index(m) + 1, total, model_name(m))
        if self.reduced:
            sweep_reduced(self, ms, progress)

    def start(self) -> _Model:
        pm0 = ParamMap(0, self.bounds)
        a_nom = self.runs[0].rig.nominal_wave_speed_m_s
        for r in self.runs:
            r.set_friction((a_nom, [], []))
        a0 = scan_wave_speed(self.stage("c", None), pm0, a_nom)
        return self.evaluate(Sol(pm0.pack(a0, []), math.nan, pm0))

    def fit_model(self, m: int, base: _Model) -> _Model:
        pm = ParamMap(m, self.bounds)
        ref = self.final.get((m - 1, False))
        if ref is not None and m >= 4 and self.saturated(m):
            self.not_searched.append(m)
            return self.embedded(pm, ref)
        if m in (1, 3) and self.runs[0].tm.active:  # the linear stand-in of the friction near this wall
            for r in self.runs:
                r.set_friction(base.sol.pm.unpack(base.sol.x))
        coarse = self.stage("c", base)
        search = coarse
        idx = self.search_parts(base)
        if len(idx) < len(self.runs):
            search = self.stage("c", base, idx)
        a_base = base.sol.pm.unpack(base.sol.x)[0]
        cands = nested_starts(base.sol, pm, self.bounds, self.tau_lo, self.tau_hi)[:-1] if base.sol.pm.m else []
        if m <= 3 and not (m == 3 and self.saturated(m)):
            grids = tau_grids(m, self.tau_lo, self.tau_hi)
            if self.max_starts is not None:  # (only those the cap keeps are solved)
                grids = grids[: max(0, max(1, self.max_starts) - len(cands))]
            cands += [reduced_then_full(search, pm, g, a_base, self.method) for g in grids]
        sols = coarse_search(search, pm, cap_starts(cands, self.max_starts), self.method, self.seed + m, 60)
        if search is not coarse:  # the search's best distinct solutions ranked on every part
            kept = distinct([s.x for s in sols], RACE_KEEP)
            sols = sorted((coarse.sol(pm, x) for x in kept), key=lambda s: s.F)
        x = sols[0].x
        if continues_by_lsq(self.method, pm):
            x = coarse.lsq(pm, x, max_nfev=150, ftol=1e-12).x
        return self.nest(pm, self.polish(pm, x, base), ref)

    def nest(self, pm: ParamMap, fin: _Model, ref: _Model | None) -> _Model:
        """The nesting guard: S(m) contains ``ref``, the model below (an element can vanish); if ``fin`` fits
        worse, S(m) is polished from ``ref`` plus a vanished element, or is that embedding."""
        if ref is not None and fin.loglik(self.runs) > ref.loglik(self.runs):
            emb = self.polish(pm, pm.embed(ref.sol.pm, ref.sol.x), ref)
            fin = min((fin, emb, self.embedded(pm, ref)), key=lambda f: f.loglik(self.runs))
        return fin

    def polish(self, pm: ParamMap, x, base: _Model, first_nfev: int = 40) -> _Model:
        """Polish on the stacked polish grids with the time-domain correction at ``base``, refreshed at the
        optimum, and the runs' weights moved to their own F there (the profile likelihood's fixed point:
        iteratively reweighted least squares), until sum n_r ln F_r stops moving. Without the polish
        (``polish_full`` False) the same on the coarse grids, by the simplex with "nelder-mead" (as the single
        sweep's polish_final)."""
        best = None
        cur = base
        for it in range(REFRESHES):
            st = self.stage(self.polish_grid, cur)
            if self.polish_grid == "c" and self.method == "nelder-mead" and pm.size > 1:
                x = st.nelder_mead(pm, x).x
            else:
                x = st.lsq(pm, x, max_nfev=first_nfev if it == 0 else 20, ftol=1e-10).x
            cur = self.evaluate(Sol(pm.project(x), math.nan, pm))
            gain = best.loglik(self.runs) - cur.loglik(self.runs) if best is not None else math.inf
            if gain > 0:
                best = cur
                self.reweight(cur)
            if gain < REFRESH_GAIN:
                break
        return best

    def continue_model(self, job: tuple[int, bool], old: _Model, start: _Model | None = None) -> _Model:
        """After the runs' closures were refined: the model ``job`` = (m, reduced) polished from its previous
        optimum (no search), not above the model it contains. ``start``: ``old``'s wall evaluated under the
        refined closures."""
        pm = old.sol.pm
        if job in self.not_searched_jobs():
            return self.embedded(pm, self.final[below(job)])
        start = start if start is not None else self.evaluate(old.sol)
        self.reweight(start)  # (its own weights: the polish's result does not depend on the model polished before)
        fin = self.polish(pm, old.sol.x, start, first_nfev=25)
        if start.loglik(self.runs) < fin.loglik(self.runs):
            fin = start  # (a polish accepts only steps that lower its objective, whose weights moved)
        return self.guarded(job, fin)

    def guarded(self, job: tuple[int, bool], fin: _Model) -> _Model:
        """``fin``, or the model below with a vanished element if that fits better (S(m) contains S(m-1), S(m)r
        S(m-1)r, S1r EL)."""
        ref = self.final.get(below(job))
        if ref is not None and fin.loglik(self.runs) > ref.loglik(self.runs):
            return self.embedded(fin.sol.pm, ref)
        return fin

    def embedded(self, pm: ParamMap, ref: _Model) -> _Model:
        return _Model(Sol(pm.embed(ref.sol.pm, ref.sol.x), ref.sol.F, pm), ref.heads, ref.F_runs)

    def not_searched_jobs(self) -> list[tuple[int, bool]]:
        return [(m, False) for m in self.not_searched]

    def saturated(self, m: int) -> bool:
        f1, f2 = self.final.get((m - 1, False)), self.final.get((m - 2, False))
        if f1 is None or f2 is None:
            return False
        return not pays(f2.loglik(self.runs) - f1.loglik(self.runs))

    def reweight(self, model: _Model) -> None:
        for r, F in zip(self.runs, model.F_runs):
            r.var = float(F)

    # ------------------------------------------------------------ summary
    def pooled(self, fin: _Model) -> tuple[float, float, float]:
        """(F, rho, s_e^2) of ``fin`` over the parts: F = exp(sum n_r ln F_r / N), and each part's residual lag-1
        and AR(1) innovation variance pooled (velab.fitting.selection.pooled_ar1) -- the summary's."""
        terms = []
        for r, h in zip(self.runs, fin.heads):
            raw = h - r.rec.h
            res = fitted(raw, r.steady_n)  # (with the part's steady head offset, velab.fitting.offset)
            rho = lag1(res)
            base_term = (objective(raw, r.steady_n) - sumsq(res)) / r.n
            terms.append((r.n, rho, ar1_innovation_var(res, rho) + base_term))
        n_tot = sum(r.n for r in self.runs)
        rho_p, innovation_var = pooled_ar1(terms, n_tot)
        return math.exp(fin.loglik(self.runs) / n_tot), rho_p, innovation_var

    def criterion(self, fin: _Model, k_nuisance: int) -> float:
        """The selection criterion of ``fin`` as its summary gives it to apply_criteria (AIC_AR1 of the pooled
        terms, or the white AIC; k = the wall's 2m + 1 plus ``k_nuisance``), without the summary's Jacobian."""
        n_tot = sum(r.n for r in self.runs)
        k = fin.sol.pm.size + k_nuisance
        if self.selection == "ar1":
            _, rho, innovation_var = self.pooled(fin)
            return aic_ar1(n_tot, k, innovation_var, rho)
        return aic_of(fin.loglik(self.runs), k)

    def summarise(self, job: tuple[int, bool], fin: _Model, k_nuisance: int, nuisance=None) -> ModelFit:
        """The ModelFit of the joint wall: standard errors from the stacked weighted Jacobian at the fit
        rate (weights 1/F_r; inflated for the residuals' lag-1 as for one run), marginalised over the records'
        fitted closures (``nuisance``: per record, its parts' indices -- consecutive -- and each part's closure
        rows, velab.fitting.parts.Part.closure_rows: one closure drives every section of its record, so its
        columns run over all of them, one block per record); F, AIC over the parts."""
        saved = [r.var for r in self.runs]
        for r, F in zip(self.runs, fin.F_runs):
            r.var = float(F)
        st = self.stage("f", fin)
        # the stacked head and Jacobian at the fit rate, once: the summary's and the closures' marginalisation
        st_head, st_jac = st.ev.head_jac_x(*fin.sol.pm.unpack(fin.sol.x), fin.sol.pm.tau_free)
        # (a model's own evaluations are not counted apart: the sweep's total, ``count``, is the result's)
        f = summarise(st, fin.sol, model_name(*job), self.runs[0].rig, self.bounds, head_jac=(st_head, st_jac))
        n_tot = sum(r.n for r in self.runs)
        blocks, slices = [], []
        for idx, rows in nuisance or ():
            if any(b.size for b in rows):
                sl = st.ev.slices()
                s0, s1 = sl[idx[0]].start, sl[idx[-1]].stop
                # the record's closure columns, its parts' offsets projected out as from the wall's
                own = tuple((i - s0, j - s0, nb) for i, j, nb in st.baseline if s0 <= i and j <= s1)
                blocks.append(project(np.concatenate([st.ev.weights[i] * b for i, b in zip(idx, rows)], axis=1), own))
                slices.append(slice(s0, s1))
        if blocks:
            res = st_head - st.d
            f = marginalised(f, fin.sol.pm, fin.sol.x, project(st_jac, st.baseline), blocks, slices, [1.0] * len(blocks),
                             objective(res, st.baseline) / res.size, lag1(fitted(res, st.baseline)), self.runs[0].rig)
        for r, v in zip(self.runs, saved):
            r.var = v
        F, rho_p, innovation_var = self.pooled(fin)
        ratio = None
        if all(r.noise_var for r in self.runs):
            ratio = math.exp(sum(r.n * math.log(F_r / r.noise_var) for r, F_r in zip(self.runs, fin.F_runs)) / n_tot)
        return replace(f, n=n_tot, F=F, k=f.k + k_nuisance, lag1_autocorr=rho_p,
                       innovation_var=innovation_var, noise_ratio=ratio)


def fit_joint(sources: list[CampaignRun], window_s: float | None = 20.0, options: FitOptions | None = None, *,
              progress=None, **choices) -> JointResult:
    """Calibrate one wall on several runs of one pipe (see the module docstring), every section of each.
    ``sources``: the runs (``CampaignRun``), two or more; ``options`` / ``choices`` as ``fit_record`` (every
    search option: ``search_options``). Raises DataError (one line, naming the run) for runs
    of different pipes, a window a run does not hold, bad options, a run whose heads do not match its rig's
    transducers."""
    if len(sources) < 2:
        raise DataError("a joint fit needs two or more runs")
    opts = FitOptions.of(options, **choices).replace(window_s=window_s)
    ms, selection, manoeuvre = list(opts.models), opts.selection, opts.manoeuvre
    tau_min_s, tau_max_s, friction, friction_unsteady = opts.tau_min_s, opts.tau_max_s, opts.friction, opts.friction_unsteady
    check_same_pipe(sources)
    t0 = time.perf_counter()

    def make(s):
        return Record(s.path, s.time_s, s.heads(), s.trigger_time_s, s.rig, window_s, record_rate_hz=s.record_rate_hz,
                      position_pct=s.position_pct, manoeuvre=manoeuvre, friction=friction,
                      friction_unsteady=friction_unsteady)

    # one after the other: a record's closure fit is many small numpy steps, each dropping and taking the GIL
    # again, and two threads of them hand it over at every step (benchmarks/fit_joint.py: the five closures took
    # 1.5 x their serial wall time on two threads, at 3 x the CPU)
    records = [make(s) for s in sources]
    parts = [p for r in records for p in r.parts]  # record after record: each record's parts consecutive
    dt = min(float(p.rec.t[1] - p.rec.t[0]) for p in parts)
    bounds = derive_bounds(parts[0].rig, dt, max(p.rec.window_s for p in parts), tau_min_s=tau_min_s,
                           tau_max_s=tau_max_s)
    sw = StackedSweep(parts, bounds, selection, progress, **search_options(opts))
    sw.sweep(ms, progress)
    refine_closures(sw, records, ms)
    top = min(sw.final.values(), key=lambda f: f.loglik(parts))
    sw.reweight(top)
    k_nuis = sum(r.vi.k for r in records)
    groups = closure_groups(parts, records, top)  # (at the top wall: once, not once a model)
    fits = [sw.summarise(job, sw.final[job], k_nuis, groups) for job in sw.jobs(ms)]
    apply_criteria(fits, selection, (bounds.tau_min_s, bounds.tau_max_s))
    result = JointResult(n=fits[0].n, window_s=max(p.rec.window_s for p in parts),
                         sample_rate_hz=min(p.rec.fit_rate_hz for p in parts), method="joint", settings={},
                         models=fits, selection=selection)
    best = result.best
    result.settings = _settings(records, ms, bounds, selection, sw, k_nuis, tau_min_s, tau_max_s)
    result.runs, result.warnings = _per_run(records, sources, sw, sw.final[(best.m, best.reduced)], best, bounds)
    if all(r["disagrees"] for r in result.runs):
        # every run beyond its noise: the model (or the rig files), not one run, does not describe them
        result.warnings.insert(0, {"code": "misfit", "message": f"the best model {best.name} leaves residuals above "
                                   f"the noise in every run: its wall is not the pipe's; check the rig files, the "
                                   f"valve, air, friction, and the models fitted"})
    result.record_rate_hz = max(p.rec.record_rate_hz for p in parts)
    result.anti_alias_filter = "per run (runs[].anti_alias_filter)"
    pool_baseline(result, parts)
    result.adequacy["per_run"] = "the misfit rule is applied to each run (runs[].misfit_bound, runs[].disagrees)"
    if best.at_bounds:
        result.warnings.append({"code": "bound", "message": bound_message(best)})
    if best.model_error_elements:
        result.warnings.append({"code": "model_error", "message": model_error_message(best)})
    n_sec = len(parts)
    result.notes.append(f"joint fit of {len(records)} runs" + (f" ({n_sec} sections)" if n_sec > len(records) else "")
                        + f": one wall (a, J_k, tau_k) shared; per run its own steady state, friction at its Q0, flow "
                          f"at the valve ({k_nuis} nuisance parameters in all, counted in k) and noise"
                        + (", each section its own noise" if n_sec > len(records) else "")
                        + "; -2 ln L = sum over runs" + (" and sections" if n_sec > len(records) else "")
                        + " of n_r ln F_r (each one's variance its own)")
    result.notes.extend(sweep_notes(sw, several=True))
    result.duration_s = time.perf_counter() - t0
    result.evaluations = sw.count.evaluations
    return result


def refine_closures(sw: StackedSweep, records: list[Record], ms) -> None:
    """The fitted closures refined with the first pass's best wall on each record's window's first part (the
    velab.fitting.parts.first_part_s, Record.refine: that wall was calibrated under the early-window
    closure, and refined from it on the whole window the closure made up for the wall's error), driving the
    whole window; then every model within CONTINUE_MARGIN of the best continued from its optimum under them (the
    others evaluated there: ``sw.not_continued``). The rounds below refine on the whole window (every wave front
    carries the closure's shape), each from a wall calibrated under the closure it refines. Then the single path's closure honesty (velab.fitting.prepare):
    when the model named (the selection criterion, as the summary gives it) is not the one the closures were
    refined with, they are refined again with its wall and every model continued, at most CLOSURE_ROUNDS times
    and only while a closure moves; and the nearest smaller rival within RIVAL_DAIC of the named model is
    compared under the closures refined with its own wall (``_own_closures``). What they did:
    ``sw.closure_notes``. The reduced models take part as in the single path: one can be the first pass's best
    or the model named (the closures then refined with its wall), not a rival (velab.fitting.prepare._own_closures
    compares full models only)."""
    if not any(r.vi.source == "fitted" for r in records):
        return
    for _ in range(REFINE_PASSES):
        _refine_and_continue(sw, records, ms, _first_pass_best(sw, ms), always=True, first_part=True)
    k_nuis = sum(r.vi.k for r in records)
    for _ in range(CLOSURE_ROUNDS):
        named = _named(sw, ms, k_nuis)
        if all(r.vi.source != "fitted" or not r.vi.refined_with or r.vi.refined_with == model_name(*named)
               for r in records):
            break
        before = records[0].vi.refined_with if len(records) == 1 else "another model"
        if not _refine_and_continue(sw, records, ms, named):
            break  # (the refinement found no better closure for that model)
        sw.closure_notes.append(f"the closure{'s' if len(records) > 1 else ''} refined again with the "
                                f"{model_name(*named)} wall (the model named under those refined with {before}'s), "
                                f"every model continued")
    _own_closures(sw, records, ms, k_nuis)


def _named(sw: StackedSweep, ms, k_nuis: int) -> tuple[int, bool]:
    """The model (m, reduced) the fit names: the least selection criterion of those it reports (``sw.jobs``;
    ties to the first: the smaller, a full model before a reduced one), as summarised."""
    return min(sw.jobs(ms), key=lambda job: sw.criterion(sw.final[job], k_nuis))


def _refine_and_continue(sw: StackedSweep, records: list[Record], ms, job: tuple[int, bool], always: bool = False,
                         first_part: bool = False) -> bool:
    """Each record's fitted closure refined with the wall of the model ``job`` (on its window's first part:
    velab.fitting.parts.Record.refine) and, if one moved (or ``always``), every model continued under them
    (``_continue_all``); whether one moved."""
    wall = sw.final[job]
    p = wall.sol.pm.unpack(wall.sol.x)
    moved = any(map_each(lambda r: r.refine(p, sw.bounds, first_part, model_name(*job)), records))
    if moved or always:
        _continue_all(sw)
    return moved


def _continue_all(sw: StackedSweep) -> None:
    """Every model fitted (the full family, then the reduced: each after the one it contains) within
    CONTINUE_MARGIN of the best (white AIC at its wall under the records' present closures) polished again from
    its optimum, the others evaluated there (``sw.not_continued``)."""
    order = sorted(sw.final, key=lambda job: (job[1], job[0]))
    skip = sw.not_searched_jobs()
    at = {job: sw.evaluate(sw.final[job].sol) for job in order if job not in skip}
    best = min(f.white_aic(sw.runs) for f in at.values())
    margin = continue_margin(sw.runs)
    sw.not_continued = []
    for job in order:
        if job in at and at[job].white_aic(sw.runs) > best + margin:
            sw.not_continued.append(job)
            sw.final[job] = sw.guarded(job, at[job])
        else:
            sw.final[job] = sw.continue_model(job, sw.final[job], at.get(job))


def _own_closures(sw: StackedSweep, records: list[Record], ms, k_nuis: int) -> None:
    """The named model against its nearest smaller rival within RIVAL_DAIC, each under the closures refined
    with its own wall (velab.fitting.prepare._own_closures: the closure is a nuisance shared by every model, so
    AIC compares the models at their own optimum over it; a closure refined with one wall favours that model).
    The rival wins when the continuation under its closures names it and its criterion there is below the
    named model's under its own: then every model stays under the rival's closures; else all is put back. Not
    tried when the closures are the rival's own already (last moved by a refinement with its wall: the named
    model was better under them). The named model may be a reduced one, a rival is not (the single path's rule)."""
    jobs_ = sw.jobs(ms)
    crit = {job: sw.criterion(sw.final[job], k_nuis) for job in jobs_}
    named = min(jobs_, key=crit.get)
    rivals = [job for job in jobs_ if not job[1] and job[0] < named[0] and math.isfinite(crit[job])
              and crit[job] - crit[named] < RIVAL_DAIC]
    fitted_ = [r for r in records if r.vi.source == "fitted" and r.vi.refined_with]
    if not rivals or not fitted_:
        return
    rival = min(rivals, key=crit.get)
    if all(r.moved_with == model_name(*rival) for r in fitted_):
        return
    saved = (dict(sw.final), list(sw.not_continued), [r.var for r in sw.runs], [r.state() for r in records])
    if _refine_and_continue(sw, records, ms, rival):
        again = _named(sw, ms, k_nuis)
        if again == rival and sw.criterion(sw.final[rival], k_nuis) < crit[named]:
            sw.closure_notes.append(f"{model_name(*rival)} under the closure refined with its own wall is better "
                                    f"than {model_name(*named)} under its own: the closure is {model_name(*rival)}'s")
            return
    sw.final, sw.not_continued = saved[0], saved[1]
    for r, v in zip(sw.runs, saved[2]):
        r.var = v
    for r, state in zip(records, saved[3]):
        r.restore(state)


def continue_margin(parts) -> float:
    """The AIC gap beyond which a model is not polished again after the closures' refinement (CONTINUE_MARGIN)."""
    return max(CONTINUE_MARGIN, CONTINUE_MARGIN_PER_SAMPLE * sum(p.n for p in parts))


def closure_groups(parts, records: list[Record], top: _Model) -> list:
    """Per record: its parts' indices and each part's closure rows at the best-fitting wall (for the wall's
    covariance marginalised over the records' closures, ``StackedSweep.summarise``)."""
    p_top = top.sol.pm.unpack(top.sol.x)
    rows = map_each(lambda p: p.closure_rows(p_top), parts)
    out, i = [], 0
    for r in records:
        idx = list(range(i, i + len(r.parts)))
        out.append((idx, [rows[j] for j in idx]))
        i += len(r.parts)
    return out


def pool_baseline(result: SweepResult, parts) -> None:
    """The parts' baseline noise pooled as F is (n-weighted geometric mean, so that a model's noise_ratio is
    F / noise^2), its lag-1 averaged, and the adequacy's sample count."""
    if all(p.noise_var for p in parts):
        result.baseline_noise_m = math.exp(sum(p.n * math.log(p.noise_var) for p in parts) / (2 * result.n))
        result.baseline_lag1 = float(np.average([p.rec.baseline_lag1 for p in parts], weights=[p.n for p in parts]))
    result.adequacy = {"baseline_samples": int(sum(p.rec.baseline_samples for p in parts)), "misfit_bound": None}


def _first_pass_best(sw: StackedSweep, ms) -> tuple[int, bool]:
    """The model (m, reduced) of the first pass with the least white AIC (sum n_r ln F_r + 2 k, k the wall's
    2m + 1, m + 1 for a reduced one), of those reported."""
    return min(sw.jobs(ms), key=lambda job: sw.final[job].white_aic(sw.runs))


def _settings(records, ms, bounds, selection, sw, k_nuis, tau_min_s, tau_max_s) -> dict:
    tm = records[0].parts[0].tm
    return {"models": ms, **search_settings(sw), "selection": selection, "joint": True,
            "bounds": bounds.to_dict(), "tau_min_s": tau_min_s, "tau_max_s": tau_max_s,
            "tau_start_range_s": [sw.tau_lo, sw.tau_hi], "not_searched": [model_name(m) for m in sw.not_searched],
            "not_continued": [model_name(*job) for job in sw.not_continued],
            "k_shared": "2m + 1" + (" (m + 1 for S1r..S5r)" if sw.reduced else ""), "k_nuisance": k_nuis,
            "sections": sum(len(r.parts) for r in records),
            "likelihood": "sum over runs (and their sections) of n_r ln F_r (Gaussian, each one's own variance "
                          "profiled out)",
            "friction": {"steady": tm.steady, "unsteady": tm.unsteady, "time_domain": tm.active,
                         "text": "each run's head is its time-domain model (its own Q0) at the wall, fitted through "
                                 "its frequency model plus a correction refreshed at the optimum"
                                 if tm.active else tm.describe()}}


def search_options(opts: FitOptions) -> dict:
    """The StackedSweep's search keywords from a fit's options: every search option of the single sweep."""
    return {"method": opts.method, "starts": opts.starts, "seed": opts.seed, "polish": opts.polish,
            "reduced": opts.reduced}


def search_settings(sw: StackedSweep) -> dict:
    """What the stacked fit's settings say of its search: the reduced models, the polish, the starts' cap, the
    seed, the method."""
    return {"reduced": sw.reduced, "polish": sw.polish_full, "starts": sw.max_starts, "seed": sw.seed,
            "method": sw.method}


def sweep_notes(sw: StackedSweep, several: bool) -> list[str]:
    """What the stacked sweep tells a reader of its fit: the models not searched, those not continued after the
    closures' refinement, the search's options (``search_notes``) and what the closures' rounds did; ``several``:
    the fit has several closures (a campaign's runs), else one (a record's)."""
    closures, closures_of = ("closures", "closures'") if several else ("closure", "closure's")
    out = []
    if sw.not_searched:
        out.append(", ".join(model_name(m) for m in sw.not_searched)
                   + ": not searched, the model below plus vanished elements (its element did not pay its AIC price)")
    if sw.not_continued:
        out.append(", ".join(model_name(*job) for job in sw.not_continued)
                   + f": not polished again after the {closures_of} refinement "
                     f"(behind the best by more than {continue_margin(sw.runs):.0f} in AIC): the wall before it under "
                     f"the refined {closures}")
    return out + search_notes(sw) + sw.closure_notes


def search_notes(sw: StackedSweep) -> list[str]:
    """The notes of a stacked fit's search that is not the default (what F means without the polish)."""
    out = []
    if sw.method != "auto":
        out.append({"least-squares": "method least-squares: each model from one start (the model below's, or the "
                                     "first tau grid's) by least squares",
                    "nelder-mead": "method nelder-mead: the coarse search by the simplex from every start",
                    "evolution": "method evolution: the coarse search also by differential evolution over the whole "
                                 f"box (seed {sw.seed} + m), seeded with the first start"}[sw.method]
                   + " (EL: the wave-speed scan, as every method)")
    if sw.max_starts is not None and sw.method != "least-squares":
        out.append(f"at most {sw.max_starts} coarse start{'s' if sw.max_starts > 1 else ''} a model")
    reduced = sorted(m for m, red in sw.final if red)
    if reduced:
        out.append(f"reduced models S1r..S{reduced[-1]}r: retardation times fixed at "
                   f"{', '.join(f'{t:g}' for t in REDUCED_RETARDATION_TIMES_S[:reduced[-1]])} s, the wave speed and "
                   f"the compliances fitted, each from the one below (S1r from EL)")
    if not sw.polish_full:
        q = sorted({r.qc for r in sw.runs})
        out.append("no polish: each model's wall is fitted (its time-domain refreshes and weights too) on the "
                   f"low-passed data decimated by {'/'.join(map(str, q))}, not on the polish grid; F is still each "
                   "part's model head at that wall against every sample of the window (pooled over the parts), at "
                   "the coarse grids' optimum, not the polish grids'")
    return out


def assess_parts(best: ModelFit, parts, fin: _Model, first: int, method: str):
    """The single fit's misfit rule on each part (``assess_part``) under the stacked fit's wall ``fin``;
    ``first``: the index of ``parts[0]`` in the sweep. Per part a dict (name, position_m, n, F, noise_ratio,
    baseline_noise_m, steady_head_m, misfit_bound, disagrees) and its warnings."""
    out = []
    for j, part in enumerate(parts):
        i = first + j
        sr = assess_part(best, part, fin.heads[i], float(fin.F_runs[i]), method)
        out.append(({"name": part.name, "position_m": part.position_m, "n": part.n, "F": float(fin.F_runs[i]),
                     "noise_ratio": sr.models[0].noise_ratio, "baseline_noise_m": part.rec.baseline_noise_m,
                     "steady_head_m": part.rec.steady_head_m,
                     "steady_head_offset": offset(fin.heads[i] - part.rec.h, part.steady_n),
                     "misfit_bound": sr.adequacy.get("misfit_bound"),
                     "disagrees": any(w["code"] == "misfit" for w in sr.warnings)}, sr.warnings))
    return out


def _per_run(records, sources, sw: StackedSweep, fin: _Model, best: ModelFit, bounds):
    """Per run: its F and noise ratio under the joint wall (pooled over its sections as F is), whether it
    disagrees (the single fit's misfit rule on each of its sections: velab.fitting.adequacy.assess), its
    sections' own ratios when it has several, and its own wall under the best model (a polish from the joint
    wall on that run alone, every section of it) for the campaign figure."""
    out, warnings = [], []
    first = [0]
    for r in records[:-1]:
        first.append(first[-1] + len(r.parts))
    owns = map_each(lambda k: _own_wall(sw, list(range(first[k], first[k] + len(records[k].parts))), fin, best.name,
                                        bounds), list(range(len(records))))
    for k, rec in enumerate(records):
        secs = assess_parts(best, rec.parts, fin, first[k], "joint")
        for (sec, ws), part in zip(secs, rec.parts):
            where = "" if len(rec.parts) == 1 else f"section {part.name} ({part.position_m:g} m): "
            for w in ws:
                warnings.append({"code": w["code"], "message": f"{rec.label}: {where}{w['message']}", "run": rec.label}
                                | ({"section": part.name} if len(rec.parts) > 1 else {}))
        n = sum(p.n for p in rec.parts)
        valve = rec.valve.rec
        own = owns[k]
        row = {
            "path": rec.label, "head_sha256": sources[k].head_sha256, "n": n, "window": valve.window_s,
            "sample_rate_hz": valve.fit_rate_hz, "record_rate_hz": valve.record_rate_hz,
            "anti_alias_filter": valve.filter, "steady_flow_m3_s": rec.rig.steady_flow_m3_s,
            "steady_head_m": valve.steady_head_m,
            "steady_head_offset": secs[rec.parts.index(rec.valve)][0]["steady_head_offset"],
            "F": math.exp(sum(s["n"] * math.log(s["F"]) for s, _ in secs) / n),
            "noise_ratio": _pooled_ratio([s for s, _ in secs]),
            "baseline_noise_m": valve.baseline_noise_m,
            "misfit_bound": secs[0][0]["misfit_bound"] if len(secs) == 1 else None,
            "disagrees": any(s["disagrees"] for s, _ in secs),
            "warnings": sorted({w["code"] for _, ws in secs for w in ws}),
            "manoeuvre": rec.vi.describe(),
            "own": {"model": best.name, "wave_speed": own.wave_speed_m_s, "wave_speed_se": own.wave_speed_se_m_s,
                    "F": own.F, "elements": own.elements(), "cov_x": own.cov_x,
                    "creep": creep_curve(own, t_min_s=bounds.tau_min_s, t_max_s=valve.window_s).to_dict()},
        }
        if len(rec.parts) > 1:
            row["sections"] = [s for s, _ in secs]
        out.append(row)
    return out, warnings


def _pooled_ratio(secs: list[dict]):
    """The sections' noise ratios pooled as F is (n-weighted geometric mean), None if one has none."""
    if any(s["noise_ratio"] is None for s in secs):
        return None
    return math.exp(sum(s["n"] * math.log(s["noise_ratio"]) for s in secs) / sum(s["n"] for s in secs))


def _own_wall(sw: StackedSweep, idx: list[int], fin: _Model, name: str, bounds) -> ModelFit:
    """The best model's wall (``name``'s; a reduced one's taus stay fixed) fitted on one run alone -- its parts
    ``idx``, every section of it -- from the joint wall (polish grids -- the coarse ones without the polish,
    ``sw.polish_grid`` --, the time-domain correction at the joint wall, one refresh, each section weighted by its
    joint F), summarised at the fit rate; its F pooled over the sections as the joint F is."""
    parts = [sw.runs[i] for i in idx]
    weights = [1.0] if len(parts) == 1 else [1.0 / math.sqrt(float(fin.F_runs[i])) for i in idx]
    pm = fin.sol.pm
    x = fin.sol.x
    heads = [fin.heads[i] for i in idx]

    def data(grid, heads, x):
        out = []
        for r, h in zip(parts, heads):
            ev, q = {"c": (r.ev_c, r.qc), "m": (r.ev_m, r.qm), "f": (r.ev_f, 1)}[grid]
            if not r.tm.active:
                out.append(lowpass_decimate(r.rec.h, q) if q > 1 else r.rec.h)
            else:
                dcorr = r.rec.h - h
                out.append((lowpass_decimate(dcorr, q) if q > 1 else dcorr) + ev.head(*pm.unpack(x)))
        return out

    grid = sw.polish_grid
    for _ in range(2):
        st = StackedEvaluator([r.ev_m if grid == "m" else r.ev_c for r in parts], weights, sw.count)
        x = Stage(st, st.stack(data(grid, heads, x)), baseline_blocks(parts, st)).lsq(pm, x, max_nfev=30, ftol=1e-10).x
        heads = [r.model_head(pm.unpack(x)) for r in parts]
    st = StackedEvaluator([r.ev_f for r in parts], weights, sw.count)
    f = summarise(Stage(st, st.stack(data("f", heads, x)), baseline_blocks(parts, st)), Sol(x, math.nan, pm),
                  name, parts[0].rig, bounds)
    if len(parts) == 1:
        return f
    n = sum(r.n for r in parts)
    return replace(f, n=n, F=math.exp(sum(r.n * math.log(objective(h - r.rec.h, r.steady_n) / r.n)
                                          for r, h in zip(parts, heads)) / n))
