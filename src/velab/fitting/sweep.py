"""Calibration sweep EL, S1..S6 (and the reduced models) with a coarse-to-fine strategy.

Default method ``"auto"`` (see docs/fitting.md):

1. Coarse stage. The window is low-passed (ideal DCT filter) at the Nyquist frequency of a
   decimated grid that still holds the manoeuvre's band (about 100 Hz sampling at the
   reference rig), and the band-limited model is evaluated on that grid. On it, every model
   is calibrated from several starts (velab.fitting.starts) by a bounded Levenberg-Marquardt
   solver (velab.fitting.solvers) with the analytic Jacobian, in the variables
   (ln a, ln J'_k, ln tau_k) of velab.fitting.params.
2. Fine stage ("polish"): the best distinct coarse solutions are refined on the full-band
   model against every sample of the window (two candidates at once in two threads, or one
   with each evaluation split over two threads).
3. Friction (velab.fitting.friction): with a quadratic steady friction the fitted head is the
   frequency model plus a time-domain correction, refreshed at the model's optimum until it
   stops moving.
4. Nesting guard: every model contains the smaller ones of its family (an element can
   vanish), so F(S(m)) <= F(S(m-1)): if the search ends above, S(m) is polished from S(m-1)
   plus a vanished element, and if that still ends above, it *is* S(m-1) plus a vanished
   element (reported as "S(m) = S(m-1) + negligible element").

Other methods replace the coarse local solver: ``"least-squares"`` (one start),
``"nelder-mead"`` (the paper's algorithm, on the coarse objective, from the same starts) and
``"evolution"`` (scipy's differential evolution over the whole box, seeded with the nested
start). All of them end with the same polish (unless ``polish=False``) and the same guard.
"""

from __future__ import annotations

import math
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable

import numpy as np

from velab.rig import Rig
from velab.errors import DataError
from velab.fitting.data import lowpass_decimate, prepare_window
from velab.fitting.engine import HeadEvaluator, sumsq
from velab.fitting.offset import counted_on, project
from velab.fitting.options import MAX_M, METHODS, FitOptions, parse_models
from velab.fitting.friction import EquivalentFriction, TimeDomainModel, anderson, equivalent_friction, fit_rig, rms
from velab.fitting.parallel import map_each
from velab.fitting.params import FitBounds, ParamMap, creep_const, derive_bounds
from velab.fitting.results import ModelFit, SweepResult, model_name
from velab.fitting.selection import ELEMENT_PRICE, apply_criteria, pays, white_aic
from velab.fitting.solvers import Sol, Stage, levenberg_marquardt
from velab.fitting.starts import (cap_starts, coarse_search, continues_by_lsq, fan_out, nested_starts, reduced_then_full,
                                  scan_wave_speed, split_all, tau_grids)
from velab.fitting.nesting import hand_back
from velab.fitting import stackreduced
from velab.fitting.summary import summarise
from velab.model import manoeuvre_band_hz

# friction correction: refreshed until it moves less than this fraction of the residual rms,
# or a refresh gains less than this in n ln F (the objective has stopped moving)
REFRESH_TOL = 0.01
REFRESH_MIN_GAIN = 0.05
MAX_REFRESH = 8
# the full-band polish of S4-S6 stops when 10 evaluations gain less than this in n ln F (AIC is
# reported to 0.01): on their flat J-tau ridge it went on for tens of full-band evaluations. Not
# below S4, and not the coarse crawl: where a smaller model ends decides the next one's nested
# starts (stopping S2 early sent S3 of the Brunone truth, tests/fitting/test_fit_truths.py, to a worse basin).
STALL_GAIN = 0.002
STALL_FROM_M = 4
# S(m) is searched from S(m-1)'s nested starts only when S(m-1)'s element did not pay its AIC price
# (velab.fitting.selection.pays): see _Sweep.saturated
SATURATION = True
# from S4 on, a saturated S(m) is not searched at all: it is S(m-1) plus a vanished element (_Sweep.nothing_left)
NOTHING_LEFT = True
# with two threads: full-band evaluations split over both (HeadEvaluator workers=2), coarse starts
# shared out over both (velab.fitting.starts.fan_out); same results either way. (Switches for
# benchmarks/fit_sweep.py's "previous sweep", which had neither.)
SPLIT_FULL_BAND = True
PARALLEL_STARTS = True
# the equivalent linear friction is matched on the coarse grid (_Sweep.equivalent)
COARSE_EQUIVALENT = True
# with a nonlinear law, the models within MOC_POLISH_AIC (white AIC) of the least, at most
# MOC_POLISH_MAX of them, end on the time-domain model's own optimum (_Sweep.polish_time_domain)
MOC_POLISH = True
MOC_POLISH_AIC = 15.0
MOC_POLISH_MAX = 3
MOC_POLISH_ITERATIONS = 6
MOC_POLISH_STEP = 1e-5  # finite-difference step in the log variables
# the polish stops where a step gains (or the Jacobian predicts) less than this in n ln F: the AIC is
# reported to 0.01, and a parameter left that far from the optimum is ~0.03 of its standard error off
# (a relative 1e-9 in F made each polish 30-36 MOC runs on the benchmark's records, where the defect
# correction had stopped 5e-4 short of the optimum)
MOC_POLISH_GAIN = 1e-3
# one finite-difference Jacobian (a MOC run per parameter) at the defect correction's end, which is
# near the optimum, then Broyden's update along the steps (velab.fitting.solvers.levenberg_marquardt)
MOC_POLISH_BROYDEN = True

__all__ = ["fit_sweep", "parse_models", "METHODS", "MAX_M", "prepare_window", "lowpass_decimate"]


@dataclass
class _Final:
    """A calibrated model on the final stage. With a time-domain friction model, ``h_time`` is
    the MOC head at ``sol.x`` and ``corr`` = h_time - h_FD(sol.x) under the current linear
    resistance, so that ``sol.F`` is that of the MOC head itself."""

    sol: Sol
    corr: np.ndarray
    h_time: np.ndarray | None = None
    refreshes: int = 0
    moved: float = 0.0


class _Sweep:
    """State shared by the models of one sweep: stages, bounds, friction, calibrated models."""

    def __init__(self, t, d, rig: Rig, bounds: FitBounds, method: str, polish: bool, starts, seed: int,
                 threads: int, initial: SweepResult | None, lead: SweepResult | None = None, flow=None,
                 baseline_n: float = 0.0):
        self.t, self.d, self.rig, self.bounds = t, d, rig, bounds
        self.n_b = baseline_n  # the steady head's offset fitted with every model (velab.fitting.offset)
        self.method, self.polish, self.seed, self.initial, self.lead = method, polish, seed, initial, lead
        self.trust_lead = True  # fit_sweep(trust_lead=): a model that vanished in the lead stays so
        self.threads = threads
        self.parallel_starts = threads > 1 and PARALLEL_STARTS
        self.max_starts = 1 if method == "least-squares" else starts
        dt = float(t[1] - t[0])
        self.band = manoeuvre_band_hz(rig)
        self.q = q = max(1, int((1.0 / dt) // (3.0 * self.band)))
        # the flow at the valve (velab.fitting.manoeuvre) drives every stage, the time-domain model too
        dc = lowpass_decimate(d, q)
        self.stage_c = Stage(HeadEvaluator(rig, t[::q], band_hz="auto", flow=None if flow is None else flow[::q]),
                             dc, counted_on(baseline_n, d.size, dc.size))
        self.time_model = TimeDomainModel(rig, t, flow=flow)
        # full-band evaluations are large numpy/FFT operations that release the GIL: with two threads,
        # each is split in two halves (HeadEvaluator workers=2), or two candidates are polished at once
        # on a pair of single-threaded evaluators (same model, own buffers); the result is the same
        workers = min(threads, 2) if SPLIT_FULL_BAND else 1
        full = (HeadEvaluator(rig, t, band_hz=None, workers=workers, flow=flow)
                if polish or self.time_model.active else None)
        self.stage_f = Stage(full, d, baseline_n) if polish else None
        self.ev_full = full  # the full-band model the friction correction is taken against
        self.ev_pair = (full.fork(workers=1), full.fork(workers=1)) if polish and threads > 1 else None
        self._counted = (0, 0)
        self.frictions: list[EquivalentFriction] = []
        self.brunone = self.time_model.unsteady == "brunone"
        window = d.size * dt
        self.tau_lo = max(2 * dt * q, bounds.tau_min_s)
        self.tau_hi = min(max(window / 2.0, 4 * self.tau_lo), bounds.tau_max_s)
        self.final: dict[tuple[int, bool], _Final] = {}
        self.not_searched: list[int] = []  # S(m) taken as S(m-1) plus a vanished element (nothing_left)
        self.as_in_lead: list[int] = []  # S(m) taken as S(m-1) plus a vanished element, as the lead fit found
        self.pm0 = ParamMap(0, bounds)
        a_nom = rig.nominal_wave_speed_m_s
        corr = np.zeros_like(d)
        if self.time_model.active:
            h0 = self.time_model.head(a_nom, [], [])
            self.set_friction(self.equivalent((a_nom, [], []), h0))
            corr = h0 - full.head(a_nom, [], [])
        self.a0 = scan_wave_speed(self.stage_c.with_data(lowpass_decimate(d - corr, q)), self.pm0, a_nom)
        x0 = self.pm0.pack(self.a0, [])
        self.start0 = _Final(Sol(x0, math.nan, self.pm0), corr, None)
        if self.time_model.active:
            self.start0 = self.with_time_head(self.pm0, x0, self.time_model.head(self.a0, [], []))

    def equivalent(self, params, h_time: np.ndarray) -> EquivalentFriction:
        """The linear friction closest to the time-domain head ``h_time`` at ``params``, compared on the
        coarse grid (the low-passed MOC head against the band-limited model): the damping it matches is
        the envelope's, well inside the band, and a comparison costs a tenth of a full-band one. It only
        sets how fast the friction refresh converges, not where (the fitted head is the MOC's)."""
        if not COARSE_EQUIVALENT or self.brunone:
            # (Brunone's friction acts on the flow's acceleration, at the wave fronts: the coarse grid
            # lacks them, and its multiple of the Vardy-Brown resistance is matched on the full band)
            return equivalent_friction(self.ev_full, params, h_time, self.brunone)
        return equivalent_friction(self.stage_c.ev, params, lowpass_decimate(h_time, self.q), self.brunone)

    def set_friction(self, eq: EquivalentFriction) -> None:
        """The frequency model's linear friction for the next model (all stages; counters carried over)."""
        self._counted = self.counts()
        self.stage_c = self.stage_c.on(self.stage_c.ev.fork(eq))
        self.ev_full = self.ev_full.fork(eq)
        if self.stage_f is not None:
            self.stage_f = self.stage_f.on(self.ev_full)
        if self.ev_pair is not None:
            self.ev_pair = (self.ev_full.fork(workers=1), self.ev_full.fork(workers=1))
        self.frictions.append(eq)

    def with_time_head(self, pm: ParamMap, x, h_time) -> _Final:
        """The model at x whose head is ``h_time`` (the MOC's): F on the final stage, exactly."""
        corr = h_time - self.ev_full.head(*pm.unpack(x))
        return _Final(self.final_stage(corr).sol(pm, x), corr, h_time)

    def current_corr(self, fin: _Final) -> np.ndarray:
        """The friction correction of a calibrated model under the current linear resistance."""
        if fin.h_time is None:
            return fin.corr
        return fin.h_time - self.ev_full.head(*fin.sol.pm.unpack(fin.sol.x))

    def current(self, fin: _Final) -> _Final:
        """``fin`` with its correction under the current linear resistance (same F)."""
        return fin if fin.h_time is None else _Final(fin.sol, self.current_corr(fin), fin.h_time, fin.refreshes,
                                                      fin.moved)

    def friction_info(self, fin: _Final) -> dict:
        """What the friction treatment did for one model (ModelFit.friction)."""
        if not self.time_model.active:
            return {}
        eq = self.ev_full.extra_impedance
        return {"refreshes": fin.refreshes, "last_change_m": fin.moved, "correction_rms_m": rms(fin.corr),
                "linear_resistance_factor": eq.factor(self.rig), "vardy_brown_factor": eq.kappa}

    @property
    def evaluators(self):
        evs = (self.stage_c.ev, self.ev_full) + (self.ev_pair or ())
        return [e for e in evs if e is not None]

    def counts(self):
        c = self._counted
        return (c[0] + sum(e.evaluations for e in self.evaluators), c[1] + sum(e.jacobians for e in self.evaluators))

    def final_stage(self, corr: np.ndarray) -> Stage:
        if self.stage_f is not None:
            return self.stage_f.with_data(self.d - corr)
        return self.stage_c.with_data(lowpass_decimate(self.d - corr, self.q))

    def local(self, stage: Stage, pm: ParamMap, x0, fine: bool) -> Sol:
        if fine:
            stall = (self.d.size, STALL_GAIN) if pm.m >= STALL_FROM_M and pm.tau_free else None
            return stage.lsq(pm, x0, max_nfev=40, ftol=1e-10, stall=stall)
        if self.method == "nelder-mead":
            return stage.nelder_mead(pm, x0)
        return stage.lsq(pm, x0, max_nfev=80, ftol=1e-10)

    def polish_final(self, stage: Stage, pm: ParamMap, x0) -> Sol:
        """Refine on the final stage (the full band, or the coarse grid without a polish)."""
        if self.stage_f is not None:
            return self.local(stage, pm, x0, fine=True)
        if self.method == "nelder-mead":
            return stage.nelder_mead(pm, x0)
        return stage.lsq(pm, x0, max_nfev=80, ftol=1e-10)

    # ------------------------------------------------------------------ one model
    def reference(self, m: int, red: bool) -> _Final | None:
        """The largest calibrated model that this one contains (S(m-1), ..., EL), if any."""
        for j in range(m - 1, -1, -1):
            f = self.final.get((j, red and j > 0))
            if f is not None:
                return f
        return None

    def fit_model(self, m: int, red: bool) -> tuple[_Final, int]:
        pm = stackreduced.param_map(m, self.bounds) if red and m else ParamMap(m, self.bounds)
        ref = self.reference(m, red)
        if ref is not None and not red and self.nothing_left(m):
            self.not_searched.append(m)
            return self.embedded(pm, self.current(ref), ref.refreshes), 0
        if ref is not None and not red and self.vanished_in_lead(m):
            self.as_in_lead.append(m)
            return self.embedded(pm, self.current(ref), ref.refreshes), 0
        start = ref if ref is not None else self.start0
        if self.time_model.active:
            # the linear friction closest to the time-domain model at the reference parameters
            px = start.sol.pm.unpack(start.sol.x)
            self.set_friction(self.equivalent(px, start.h_time))
            start = self.with_time_head(start.sol.pm, start.sol.x, start.h_time)
        base = start.sol if ref is not None else Sol(start.sol.x, math.nan, start.sol.pm)
        best, n_starts = self.calibrate(pm, red, base, start.corr, model_name(m, red))
        fin = self.refresh(pm, best, start.corr)
        if ref is not None and fin.sol.F > start.sol.F:
            fin = self.guard(pm, start, fin)
        return fin, n_starts

    def calibrate(self, pm: ParamMap, red: bool, base: Sol, corr: np.ndarray, name: str) -> tuple[Sol, int]:
        """Multi-start coarse search and full-band polish with the friction correction held fixed."""
        m = pm.m
        dc = lowpass_decimate(self.d - corr, self.q) if self.time_model.active else self.stage_c.d
        if self.stage_f is not None:
            # defect correction: the coarse (band-limited, decimated) model's error w.r.t. the
            # full-band model, at the base solution, is taken off the coarse data so that the
            # coarse minimum lands next to the full-band one.
            xb = base.pm.unpack(base.x)
            dc = dc - (lowpass_decimate(self.stage_f.ev.head(*xb), self.q) - self.stage_c.ev.head(*xb))
        stage = self.stage_c.with_data(dc)
        cands = self.starts(pm, red, base, stage, name)
        sols = coarse_search(stage, pm, cands, self.method, self.seed + m, 80, parallel=self.parallel_starts)
        if continues_by_lsq(self.method, pm):
            # the winner continues on the cheap objective until it stops moving along the ridge
            sols[0] = stage.lsq(pm, sols[0].x, max_nfev=400, ftol=1e-13)
        if self.stage_f is None:
            best = sols[0]
        else:
            fstage = self.final_stage(corr)
            pol = [sols[0].x] + [s.x for s in sols[1:2] if s.F < sols[0].F * (1 + 1e-5)
                                 and np.max(np.abs(s.x - sols[0].x)) > 0.05]
            if len(pol) > 1 and self.ev_pair is not None:
                with ThreadPoolExecutor(max_workers=1, thread_name_prefix="velab-polish") as pool:
                    fut = pool.submit(self.local, fstage.on(self.ev_pair[1]), pm, pol[1], True)
                    fsols = [self.local(fstage.on(self.ev_pair[0]), pm, pol[0], fine=True), fut.result()]
            else:
                fsols = [self.local(fstage, pm, x0, fine=True) for x0 in pol]
            best = min(fsols, key=lambda s: s.F)
        if m >= 1 and base.pm.m < m and (base.pm.m == 0 or bool(base.pm.fixed_tau) == red) and math.isfinite(base.F):
            fstage = self.final_stage(corr)
            if best.F > base.F:
                # S(m) must not fit worse than the model it contains: start from S(m-1) with an element
                # split (tau x/÷ 1.05), then cut into two equal halves (which reproduces S(m-1)), then
                # from S(m-1) plus a vanished element; the polish only accepts steps that lower F
                tries = split_all(base, pm, 1.05)[:1] + split_all(base, pm, 1.0)[:1] if pm.m == base.pm.m + 1 and base.pm.m and not red else []
                tries.append(pm.embed(base.pm, base.x))
                for x0 in tries:
                    s2 = self.polish_final(fstage, pm, x0)
                    if s2.F < best.F:
                        best = s2
                    if best.F <= base.F:
                        break
        return best, len(sols)

    def starts(self, pm: ParamMap, red: bool, base: Sol, stage: Stage, name: str) -> list[np.ndarray]:
        m = pm.m
        cands: list[np.ndarray] = []
        if self.lead is not None:
            # a continuation: the lead fit searched this record's first part, this one starts at its optimum
            old = self.lead.get(name)
            if old is not None and old.m == m and old.reduced == red:
                cands = [pm.clip(_pack_fit(pm, old, self.rig))]
                if not self.trust_lead and _vanished(old) and base.pm.m == m - 1 and not red:
                    # it vanished in the lead, under another flow: searched again from this sweep's S(m-1)
                    # with an element split or added below, between and above (a polish of the vanished
                    # element alone found it or not by the last bits of the closure)
                    cands.extend(nested_starts(base, pm, self.bounds, self.tau_lo, self.tau_hi)[:-1])
                return cands
        if self.initial is not None:
            old = self.initial.get(name)
            if old is not None and old.m == m and old.reduced == red:
                cands.append(pm.clip(_pack_fit(pm, old, self.rig)))
        if m == 0:
            cands.append(pm.pack(self.a0, []))
            return cands
        a_base = base.pm.unpack(base.x)[0]  # EL's optimum seeds S1
        if red:
            cands.extend(stackreduced.starts(pm, base))
        else:
            # S(m-1) with an element split or a small element added (the exact embedding, S(m-1)
            # plus a vanished element, is the guard's start in calibrate: it only matters when
            # every search ends above S(m-1)), then tau grids solved with tau fixed first
            if base.pm.m:
                cands.extend(nested_starts(base, pm, self.bounds, self.tau_lo, self.tau_hi)[:-1])
            if not self.saturated(m):
                cands.extend(fan_out(stage, lambda st, grid: reduced_then_full(st, pm, grid, a_base, self.method),
                                     tau_grids(m, self.tau_lo, self.tau_hi), self.parallel_starts))
        return cap_starts(cands, self.max_starts)

    def saturated(self, m: int) -> bool:
        """S(m-1)'s element did not pay for itself: n ln(F(S(m-2)) / F(S(m-1))) below the AIC price of its
        two parameters (velab.fitting.selection.pays). The data then hold no structure for one more element, and
        S(m) is searched from S(m-1)'s nested starts only (no tau-grid starts)."""
        if not SATURATION or m < 3:
            return False
        f1, f2 = self.final.get((m - 1, False)), self.final.get((m - 2, False))
        if f1 is None or f2 is None:
            return False
        return not pays(self.d.size * math.log(f2.sol.F / f1.sol.F))

    def nothing_left(self, m: int) -> bool:
        """From S4 on: S(m-1)'s element did not pay its AIC price (``saturated``), so S(m) is not searched.

        Forward selection stops at the first element that does not pay: S(m) could only be chosen
        by AIC if its own element gained more than its price (n ln F > 4) where S(m-1)'s, searched
        from every placement of one more element below, between and above S(m-2)'s, splits of them
        and tau grids, did not; S(m)'s starts would be S(m-1)'s again plus a vanished element. S(m)
        is then S(m-1) plus a vanished element (the table says so and the result's notes name
        the models). On the reference records S5 and S6 always ended there after a search that
        took a third to a half of the sweep. A lone model (``models=[5]``) is always searched."""
        return NOTHING_LEFT and m >= STALL_FROM_M and self.saturated(m)

    def vanished_in_lead(self, m: int) -> bool:
        """In the lead fit, S(m) ended as a smaller model plus vanished (or split) elements: its search over
        the record's first part found no use for one more element, and the rest of the window (the
        transient's most damped part) holds less of the structure an element would fit."""
        if not self.trust_lead:
            return False
        old = self.lead.get(model_name(m, False)) if self.lead is not None else None
        return old is not None and _vanished(old)

    def embedded(self, pm: ParamMap, ref: _Final, refreshes: int) -> _Final:
        """``ref`` (with its correction under the current linear resistance) plus vanished elements,
        as a model ``pm``: its head and its MOC head are ``ref``'s."""
        emb = self.final_stage(ref.corr).sol(pm, pm.embed(ref.sol.pm, ref.sol.x))
        return _Final(emb, ref.corr, ref.h_time, refreshes, 0.0)

    def refresh(self, pm: ParamMap, best: Sol, corr: np.ndarray) -> _Final:
        """Refresh the friction correction at the optimum and re-polish until it stops moving."""
        if not self.time_model.active:
            return _Final(best, corr)
        kept: _Final | None = None
        n = self.d.size
        xs, gs = [], []  # the fixed-point map x -> G(x) = polish under c(x), for Anderson mixing
        x = best.x
        fails = 0
        for it in range(1, MAX_REFRESH + 1):
            cur = self.with_time_head(pm, x, self.time_model.head(*pm.unpack(x)))
            cur.moved = moved = rms(cur.corr - corr)
            corr = cur.corr
            # F here is the model's own (the MOC head at its parameters): keep the best such model
            gain = n * math.log(kept.sol.F / cur.sol.F) if kept is not None else math.inf
            if gain > 0:
                kept, fails = cur, 0
            else:
                fails += 1
            kept.refreshes = it
            if (moved <= REFRESH_TOL * math.sqrt(cur.sol.F) or 0 <= gain < REFRESH_MIN_GAIN or fails >= 2
                    or it == MAX_REFRESH):
                return kept
            if gain <= 0:
                # the mixed step went uphill: restart the plain iteration from the best model
                xs, gs = [], []
                cur = kept
            g = self.polish_final(self.final_stage(cur.corr), pm, cur.sol.x).x
            xs.append(cur.sol.x)
            gs.append(g)
            x = pm.project(anderson(xs[-3:], gs[-3:]))
        return kept  # pragma: no cover (the loop returns)

    def polish_time_domain(self, fin: _Final) -> _Final:
        """The model polished on the time-domain model itself: Levenberg-Marquardt on h_MOC(p) - d with a
        finite-difference Jacobian (one MOC run per parameter). The defect correction stops where the
        frequency model's optimum under the frozen correction stops moving, which is near but not at
        the MOC's own optimum (measured: 0.1-2.5 in n ln F for models near the truth, 12 for Brunone's
        S2); the reported F, parameters and uncertainties must be the time-domain model's."""
        pm, tm = fin.sol.pm, self.time_model
        lo, hi = pm.bounds()
        cache: dict = {}

        def head(x):
            key = np.asarray(x).tobytes()
            if key not in cache:
                cache.clear() if len(cache) > 64 else None
                cache[key] = tm.head(*pm.unpack(x))
            return cache[key]

        def residual(x):  # (with the steady head's offset projected out: velab.fitting.offset)
            return project(head(x) - self.d, self.n_b)

        def column(x, h0, i):
            xp = np.array(x, dtype=float)
            step = MOC_POLISH_STEP if xp[i] + MOC_POLISH_STEP <= hi[i] else -MOC_POLISH_STEP
            xp[i] += step
            return project((tm.head(*pm.unpack(xp)) - h0) / step, self.n_b)

        def jacobian(x):
            h0 = head(x)
            # one MOC run a column, shared out over two threads (the MOC releases the GIL; each column
            # depends on its parameter only, so the Jacobian is the same whichever thread ran it)
            cols = map_each(lambda i: column(x, h0, i), list(range(x.size)))
            return np.array(cols).T

        sol = levenberg_marquardt(residual, jacobian, fin.sol.x, lo, hi, max_iter=MOC_POLISH_ITERATIONS,
                                  ftol=MOC_POLISH_GAIN / self.d.size, broyden=MOC_POLISH_BROYDEN, predicted=True)
        F = sumsq(sol.fun) / self.d.size
        if not F < fin.sol.F:
            return fin
        out = self.with_time_head(pm, sol.x, head(sol.x))
        out.refreshes, out.moved = fin.refreshes, fin.moved
        return out

    def guard(self, pm: ParamMap, ref: _Final, fin: _Final) -> _Final:
        """F(S(m)) ended above the model it contains (after the friction refresh): start S(m) from
        that model plus a vanished element, and if it still ends above, take that embedding.
        ``ref`` carries its correction under the current linear resistance."""
        x_emb = pm.embed(ref.sol.pm, ref.sol.x)
        stage = self.final_stage(ref.corr)
        cand = self.polish_final(stage, pm, x_emb)
        if self.time_model.active:
            cand_fin = self.with_time_head(pm, cand.x, self.time_model.head(*pm.unpack(cand.x)))
            cand_fin.refreshes, cand_fin.moved = fin.refreshes + 1, rms(cand_fin.corr - ref.corr)
        else:
            cand_fin = _Final(cand, ref.corr)
        if cand_fin.sol.F <= ref.sol.F and cand_fin.sol.F < fin.sol.F:
            return cand_fin
        emb = self.embedded(pm, ref, fin.refreshes)
        return emb if emb.sol.F < fin.sol.F else fin


def _vanished(f: ModelFit) -> bool:
    """``f`` ended as a smaller model plus vanished (or split) elements -- not one whose extra element is a model
    error (velab.fitting.selection.mark_model_errors: a live element, which the search must see again)."""
    return bool(f.equivalent_to) and not f.model_error_elements


def _pack_fit(pm: ParamMap, old: ModelFit, rig: Rig) -> np.ndarray:
    """x of a previous ModelFit (warm start)."""
    a = old.wave_speed_m_s
    J = np.array([creep_const(rig) * a * a / e for e in old.E_pa])
    return pm.pack(a, J, np.array(old.tau_s) if not pm.fixed_tau else None)


@dataclass(frozen=True)
class SweepContext:
    """What the fit path derives for a sweep (velab.fitting.prepare), not a user's choice (FitOptions).

    ``lead``: the sweep of this record's first part (velab.fitting.lead): each model is then calibrated from
    the lead's optimum alone (no multi-start search), and a model that ended there as a smaller one plus a
    vanished element is that again here (unless ``trust_lead`` is False: the lead was driven by another flow,
    a closure fitted on the early window and refined since, under which the closure had taken up what a fast
    element does). ``initial``: a previous SweepResult (e.g. on a shorter window) whose parameters are added
    as starts. ``flow``: the flow at the valve q(t) on the record's samples (velab.fitting.manoeuvre: from the
    recorded position or a fitted closure); None: the rig's sigmoid imposed as the flow (the paper's).
    ``time_domain_polish``: with a nonlinear friction law the competitive models end on the time-domain model's
    own optimum (False: where the defect correction stops; a sweep that only seeds a continuation).
    ``marginalise``: f, stage, sol -> f, applied to each model's summary (velab.fitting.nuisance: the covariance
    marginalised over a closure fitted from the same record). ``baseline_n``: the samples before the trigger
    that set the steady head (``h_m``'s zero), counted at the window's rate; then every model also fits the
    steady head's offset, the baseline its prior (velab.fitting.offset); 0: the steady head as ``h_m`` has it."""

    lead: SweepResult | None = None
    initial: SweepResult | None = None
    flow: object = None
    time_domain_polish: bool = True
    marginalise: Callable | None = None
    trust_lead: bool = True
    baseline_n: float = 0.0


def fit_sweep(t_s, h_m, rig: Rig, options: FitOptions | None = None, *,
              progress: Callable[[int, int, str], None] | None = None, context: SweepContext | None = None,
              **choices) -> SweepResult:
    """Calibrate EL/Sm models on a head record and rank them.

    ``t_s`` is time from the trigger (s, may start negative), ``h_m`` the head perturbation (m, head minus its
    steady pre-trigger value); the window is ``options.window_s`` after the trigger (None: all of ``t_s``).
    ``options``: the user's choices (velab.fitting.options.FitOptions; ``choices`` by name, e.g.
    ``models=[1, 2]``, change them). ``progress(done, total, name)`` is called after each model. ``context``:
    what the fit path derived (SweepContext; default: none of it). The result is the same whatever
    ``options.threads``. Pure computation: no I/O, no shared state; safe to call from worker threads.
    """
    opts = FitOptions.of(options, **choices)
    ctx = context if context is not None else SweepContext()
    models, window_s, method, reduced, polish = opts.models, opts.window_s, opts.method, opts.reduced, opts.polish
    starts, seed, tau_min_s, tau_max_s, threads = opts.starts, opts.seed, opts.tau_min_s, opts.tau_max_s, opts.threads
    selection, friction, friction_unsteady = opts.selection, opts.friction, opts.friction_unsteady
    lead, initial, flow, time_domain_polish = ctx.lead, ctx.initial, ctx.flow, ctx.time_domain_polish
    marginalise, trust_lead, baseline_n = ctx.marginalise, ctx.trust_lead, ctx.baseline_n
    t0 = time.perf_counter()
    ms = list(models)
    t, d = prepare_window(t_s, h_m, window_s)
    n = d.size
    if flow is not None:  # given on t_s: the window's part of it
        flow = np.asarray(flow, dtype=float)
        i0 = int(np.searchsorted(np.asarray(t_s, dtype=float), t[0]))
        if flow.shape != np.shape(t_s):
            raise DataError(f"the flow at the valve has {flow.size} samples, the record {np.size(t_s)}")
        flow = flow[i0 : i0 + n]
    dt = float(t[1] - t[0])
    window = n * dt
    rig = fit_rig(rig, friction, friction_unsteady)
    bounds = derive_bounds(rig, dt, window, tau_min_s=tau_min_s, tau_max_s=tau_max_s)
    if threads is None:
        threads = min(2, os.cpu_count() or 1)
    sw = _Sweep(t, d, rig, bounds, method, polish, starts, seed, threads, initial, lead, flow, baseline_n)
    sw.trust_lead = trust_lead

    jobs = stackreduced.jobs(ms, reduced)  # (the reduced family's facts: one place for both engines)
    order = sorted(jobs, key=lambda j: (j[1], j[0]))
    spent: dict = {}
    for done, job in enumerate(order, 1):
        before = sw.counts()
        fin, n_starts = sw.fit_model(*job)
        sw.final[job] = fin
        after = sw.counts()
        spent[job] = [after[0] - before[0], after[1] - before[1], n_starts]
        if progress is not None:
            progress(done, len(jobs), model_name(*job))
    # a larger model that found a better optimum along a structure a smaller one can express
    # hands it back (velab.fitting.nesting); then the order F(EL) >= F(S1) >= ... is restored
    head = [(0, False)] if 0 in ms else []
    for family in ([(m, False) for m in ms], head + [j for j in order if j[1]]):
        hand_back(sw, family, spent)
    if sw.time_model.active and MOC_POLISH and time_domain_polish:
        polished = _polish_candidates(sw, order)
    else:
        polished = []
    fits: list[ModelFit] = []
    for job in order:
        fin = sw.final[job]
        ev, jac, n_starts = spent[job]
        stage = sw.final_stage(sw.current_corr(fin))
        f = summarise(stage, fin.sol, model_name(*job), sw.rig, bounds, evaluations=ev, jacobians=jac, starts=n_starts,
                      friction=sw.friction_info(fin))
        fits.append(marginalise(f, stage, fin.sol) if marginalise is not None else f)

    apply_criteria(fits, selection, (bounds.tau_min_s, bounds.tau_max_s))
    settings = {
        "models": ms, "reduced": reduced, "polish": polish, "starts": starts, "seed": seed,
        "decimation": sw.q, "coarse_band_hz": sw.band, "tau_start_range_s": [sw.tau_lo, sw.tau_hi],
        "tau_min_s": tau_min_s, "tau_max_s": tau_max_s, "bounds": bounds.to_dict(), "selection": selection,
        "warm_start": initial is not None,
        "lead": None if lead is None else {"window_s": lead.window_s, "best": lead.best.name if lead.models else "",
                                           "evaluations": lead.evaluations, "duration_s": lead.duration_s},
        "as_in_lead": [model_name(m, False) for m in sw.as_in_lead],
        "not_searched": [model_name(m, False) for m in sw.not_searched],
        "friction": {"steady": sw.time_model.steady, "unsteady": sw.time_model.unsteady,
                     "time_domain": sw.time_model.active, "moc_runs": sw.time_model.runs,
                     "moc_seconds": sw.time_model.seconds, "text": sw.time_model.describe(sw.frictions[1:])},
    }
    result = SweepResult(
        n=fits[0].n if fits else n, window_s=window, sample_rate_hz=1.0 / dt, method=method, settings=settings,
        models=fits, duration_s=time.perf_counter() - t0, evaluations=sw.counts()[0], selection=selection,
    )
    if sw.not_searched:
        names = ", ".join(model_name(m, False) for m in sw.not_searched)
        first = sw.not_searched[0]
        result.notes.append(f"{names}: not searched, {model_name(first - 1, False)} plus vanished elements "
                            f"({model_name(first - 1, False)}'s element did not pay its AIC price: n ln F gained "
                            f"< {ELEMENT_PRICE:g} over {model_name(first - 2, False)})")
    if sw.as_in_lead:
        names = ", ".join(model_name(m, False) for m in sw.as_in_lead)
        smaller = model_name(sw.as_in_lead[0] - 1, False)
        result.notes.append(f"{names}: {smaller} plus vanished elements, as in the lead fit of the first "
                            f"{lead.window_s:.6g} s (its search there found no use for one more element)")
    if not polish:
        result.notes.append(f"no full-band polish: F on the low-passed data decimated by {sw.q}")
    if polished:
        result.notes.append(f"{', '.join(polished)}: polished on the time-domain model itself (its own optimum, "
                            f"not the defect correction's)")
    result.settings = result.settings.replace(time_domain_polish=polished)
    return result


def _polish_candidates(sw: _Sweep, order) -> list[str]:
    """The models that can compete (white AIC within MOC_POLISH_AIC of the least) polished on the
    time-domain model (``_Sweep.polish_time_domain``), in order of m; a model that is a smaller one plus
    vanished elements is that smaller one's polish again (so F never increases with m)."""
    n = sw.d.size
    aic = {job: white_aic(n, sw.final[job].sol.F, sw.final[job].sol.pm.size) for job in order}
    best = min(aic.values())
    done: list[str] = []
    for family in ([j for j in order if not j[1]], [j for j in order if j[1]]):
        prev_job, prev_before = None, None  # the previous model of the family and its solution before any polish
        for job in family:
            before = sw.final[job]
            pm = before.sol.pm
            embedding = (prev_before is not None and pm.m == prev_before.sol.pm.m + 1
                         and np.array_equal(before.sol.x, pm.embed(prev_before.sol.pm, prev_before.sol.x)))
            if embedding:
                if sw.final[prev_job] is not prev_before:  # S(m-1) moved: S(m) = S(m-1) + a vanished element follows
                    sw.final[job] = sw.embedded(pm, sw.current(sw.final[prev_job]), before.refreshes)
            elif aic[job] - best <= MOC_POLISH_AIC and len(done) < MOC_POLISH_MAX:
                sw.final[job] = sw.polish_time_domain(sw.current(before))
                done.append(model_name(*job))
            if prev_job is not None and sw.final[job].sol.pm.m == sw.final[prev_job].sol.pm.m + 1 and \
                    sw.final[job].sol.F > sw.final[prev_job].sol.F:
                # a polished smaller model below this one: this one contains it (F never increases with m)
                sw.final[job] = sw.embedded(pm, sw.current(sw.final[prev_job]), before.refreshes)
            prev_job, prev_before = job, before
    return done

