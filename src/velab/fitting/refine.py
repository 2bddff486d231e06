"""The fitted closure refined on a record's whole window with a calibrated wall (velab.fitting.closurefit's
closure, then this).

Every wave front of the window carries the closure's shape, so the whole record pins it far better than its
first part; and a fast creep element smooths the fronts as a slower closure would, so the two are solved
together, on the record low-passed and decimated to REFINE_RATE_PER_BAND x the manoeuvre's band, with the
linear friction closest to the time-domain model and the remaining difference as a correction refreshed
between the stages: (1) basins -- the first part's closure, its alternative and the prototypes
(``PROTOTYPES``), each taken START_ITERATIONS steps of a joint Levenberg-Marquardt, the best goes on;
(2) variable projection (Golub & Pereyra) -- the closure stepped on the profile residual, the wall solved
again under every closure tried. Only the closure is kept (the sweep's continuation then calibrates every
model under it); its standard errors are those of the projected Jacobian (the wall marginalised), inflated for
the residuals' lag-1. Why this way: docs/decisions.md.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from velab.fitting.data import lowpass_decimate
from velab.fitting.engine import HeadEvaluator, gram, sumsq
from velab.fitting.friction import TimeDomainModel, equivalent_friction
from velab.fitting.closure import (NV, PARAM_NAMES, closure_bounds, closure_kappa, coupling_exponent, from_solver,
                                   law_words, own_valve_starts, to_solver)
from velab.fitting.closurefit import OTHER_LAW_PRICE, STARTS, closure_standard_errors
from velab.fitting.flows import ValveInput, closure_coupling, closure_flow, coupling_model, tm_flow
from velab.fitting.params import FitBounds, ParamMap, derive_bounds
from velab.fitting.solvers import LMSolution, Stage, levenberg_marquardt
from velab.fitting.stats import lag1
from velab.model import ValveHeadModel, creep_scale, manoeuvre_band_hz, series_impedance
from velab.rig import Rig

REFINE_RATE_PER_BAND = 8.0  # the refinement runs at this multiple of the manoeuvre's band
START_ITERATIONS = 8  # each start is taken this many joint steps before the best goes on
BROYDEN = True  # the joint steps carry their Jacobian by Broyden's update (velab.fitting.solvers)
STEP = 1e-6  # finite-difference step in the solver's variables
PROJECTION_ITERATIONS = 4  # closure steps of each projection pass
PROJECTION_PASSES = 2  # with a time-domain friction: the correction refreshed between them
PROJECTION_GAIN = 0.5  # a pass stops at a step that gains less than this in n ln F (on the refinement's grid)
INNER_NFEV = 20  # the wall's solve under one closure (warm-started from the best wall so far)
JOINT_ITERATIONS = 15  # then the best start's joint steps
JOINT_PASSES = 2  # ... with the correction refreshed before each (time-domain laws)
FINALIST_ATOL = 1e-3  # a start whose closure (solver variables) ends this far from the best's goes on too
POLISH_ITERATIONS = 8  # then joint steps on the record's model on the fit's own grid (``_Refinement.polish``; 0: none)
POLISH_STEP = 1e-5  # their finite-difference step in the solver's variables
LAW_CHOICE = True  # a closure of a valve the rig file does not describe: refined under both valve laws (refine_closure)
# the prototypes' (characteristic power, loss share): manoeuvre.STARTS and a quick-opening valve, which passes half
# its flow until late in the stroke; without it, a quick-opening valve's record changed by 1e-9 m ended in a closure
# at the box's corner (power 6, loss share 0.001) that a fast element made up for, 170 in n ln F short
PROTOTYPES = tuple((power, share) for power, share, _ in STARTS) + ((0.5, 0.5),)


def refine_closure(t, d, rig: Rig, vi: ValveInput, fit, bounds: FitBounds | None = None) -> ValveInput:
    """The fitted closure ``vi`` refined on the whole window (t from the trigger, d the head perturbation)
    jointly with a calibrated wall: ``fit`` (a ModelFit: the best model of a sweep driven by ``vi``) is the
    start; ``bounds`` the sweep's box for the wall (None: derived from the rig and the window). A flow not
    fitted (recorded position, the rig's sigmoid) is returned as it is.

    A closure whose shape the record's first part showed not to be the rig file's valve (``vi.shape`` "fitted"),
    refined for the first time, is refined under both valve laws (the orifice coupling and the flow imposed as
    such: ``other_law``), and the law that fits the whole window better by more than OTHER_LAW_PRICE in n ln F is
    kept (the rig's otherwise): the first part hardly tells them apart (5.7-14.6 in n ln F on an imposed sigmoid's
    records fitted with the orifice rig file) and the orifice family's best imitation of an imposed flow moved the
    wave speed by up to 2 standard errors."""
    if vi.source != "fitted":
        return vi
    out, F_end = _refine(t, d, rig, vi, fit, bounds)
    if vi.shape != "fitted" or vi.refined_with or not LAW_CHOICE:
        return out
    kappa = closure_kappa(rig, vi)
    other = replace(vi, params=dict(vi.params, coupling=1.0 - kappa), alternatives=())
    alt, F_alt = _refine(t, d, rig, other, fit, bounds)
    n = np.size(t)
    gain = n * math.log(F_end / F_alt) if F_alt > 0 else math.inf
    ours = "the rig's" if kappa == coupling_exponent(rig) else "the first part's"
    if gain > OTHER_LAW_PRICE:
        return replace(alt, text=f"{alt.text}; under the other valve law (the coupling exponent {1.0 - kappa:g}): it "
                                 f"fits the window better by {gain:.1f} in n ln F than {ours} (more than "
                                 f"{OTHER_LAW_PRICE:g})")
    return replace(out, text=f"{out.text}; the other valve law (the coupling exponent {1.0 - kappa:g}) fitted the "
                             f"window {gain:.1f} in n ln F better than {ours}, not more than {OTHER_LAW_PRICE:g}")


def _refine(t, d, rig: Rig, vi: ValveInput, fit, bounds: FitBounds | None) -> tuple[ValveInput, float]:
    """``refine_closure`` under ``vi``'s valve law; also F of the record's model on the fit's grid at its end."""
    prob = _Refinement(t, d, rig, vi, fit, bounds)
    F_start = prob.model_F(prob.start_wall(), prob.v0)
    ends = []
    for x in prob.basins():
        # the orifice coupling takes the joint optimum's head (wall and closure) instead of the measured one, whose
        # noise entered the flow (manoeuvre.closure_coupling), and the closure is projected once under it: a
        # projection before the coupling's change as well moved the wave speed by 0.05 m/s at 10 % of the fit's cost
        coupling = coupling_model(*prob.split(x))
        prob.set_coupling(coupling)
        v, sol, wall = prob.project(x)
        wall, v = prob.polish(wall, v)
        ends.append((prob.model_F(wall, v), coupling, v, sol, wall))
    F_best, coupling, v, sol, wall = min(ends, key=lambda e: e[0])
    if len(ends) > 1:
        prob.set_coupling(coupling)
    if not F_best < F_start:
        # the refinement's model (the frequency model, its linear friction stand-in and a correction refreshed
        # between the stages) is not the time-domain model: a closure that fits it better but the record no
        # better is not taken
        name = getattr(fit, "name", "") or f"S{prob.k}"
        return replace(vi, refined_with=name, text=f"{vi.text} (refined over the whole window with the {name} wall: it "
                                                   f"fitted the record no better, so this closure was kept)"), F_start
    res = sol.fun
    F = sumsq(res) / res.size
    rho = max(0.0, min(lag1(res), 0.99))
    se = closure_standard_errors(sol, F, res.size) * math.sqrt((1 + rho) / (1 - rho))
    valve = from_solver(v)
    params = dict(zip(PARAM_NAMES, (float(p) for p in valve)))
    ses = {name: float(se[i] * params[name]) if name in ("beta_per_s", "power", "loss_share") else float(se[i])
           for i, name in enumerate(PARAM_NAMES)}
    tw = prob.t
    text = (f"flow at the valve from a fitted closure (no valve position in the record): effective opening "
            f"T(sigmoid(beta (t - t_half))) with beta = {params['beta_per_s']:.4g} +- {ses['beta_per_s']:.2g} 1/s, "
            f"t_half = {params['t_half_s'] * 1e3:.4g} +- {ses['t_half_s'] * 1e3:.2g} ms, characteristic power "
            f"{params['power']:.3g}, valve loss share {params['loss_share']:.3g}, orifice coupling "
            f"{params['coupling']:.3g} ({law_words(rig, params['coupling'])}); fitted over {tw[-1] + tw[1] - tw[0]:.4g} s "
            f"with the wall ({getattr(fit, 'name', '') or 'S' + str(prob.k)})"
            + ("; its shape held at the rig's valve" if vi.shape == "rig" else ""))
    return ValveInput("fitted", closure_flow(prob.t_full, prob.hc_full, rig, valve), params, ses, text,
                      k=vi.k, gain=prob.t_full.size * math.log(prob.F0 / F) if F > 0 else math.inf, shape=vi.shape,
                      shape_gain=vi.shape_gain,
                      refined_with=getattr(fit, "name", ""), coupling=coupling), F_best


class _Refinement:
    """The refinement's grid, models and friction correction (see the module docstring)."""

    def __init__(self, t, d, rig: Rig, vi: ValveInput, fit, bounds: FitBounds | None):
        self.rig, self.vi = rig, vi
        self.t_full = t_full = np.asarray(t, dtype=float)
        self.d_full = np.asarray(d, dtype=float)
        self.hc_full = closure_coupling(t_full, d, rig, vi.coupling)
        dt = float(t_full[1] - t_full[0])
        # on the record low-passed and decimated to REFINE_RATE_PER_BAND x the manoeuvre's band: the model
        # has nothing above it (a closure's spectrum falls exponentially) and the solve is q x cheaper
        q = max(1, int((1.0 / dt) // (REFINE_RATE_PER_BAND * manoeuvre_band_hz(rig))))
        self.q = q
        self.t, self.d, self.hc = t_full[::q], lowpass_decimate(np.asarray(d, dtype=float), q), self.hc_full[::q]
        a = fit.wave_speed_m_s
        self.J0 = creep_scale(rig, a) / np.asarray(fit.E_pa, dtype=float)
        self.tau0 = np.asarray(fit.tau_s, dtype=float)
        self.a0 = a
        self.k = self.J0.size
        self.bounds = bounds if bounds is not None else derive_bounds(rig, dt, t_full.size * dt)
        self.tm = TimeDomainModel(rig, self.t)
        flow0 = vi.flow[::q]
        self.vm = ValveHeadModel(rig, self.t, band_hz=None, flow=flow0)
        self.eq = None
        if self.tm.active:
            ev = HeadEvaluator(rig, self.t, band_hz=None, flow=flow0)
            self.eq = equivalent_friction(ev, (a, self.J0, self.tau0),
                                          self.tm.head(a, self.J0, self.tau0, flow=tm_flow(self.t, flow0)))
        self.W = series_impedance(self.vm.s_band, rig) + (0.0 if self.eq is None else self.eq(self.vm.s_band, rig))
        self.corr = np.zeros_like(self.d)
        self.clo, self.chi = closure_bounds(rig, vi.shape, closure_kappa(rig, vi))
        self._evs: dict = {}
        self.F0 = math.nan
        self.tm_full = self.vm_full = None  # the record's model on the fit's own grid (``full_head``), when needed

    def set_coupling(self, model: dict) -> None:
        """The orifice coupling taken from ``model``'s head (manoeuvre.closure_coupling) from now on."""
        self.hc_full = closure_coupling(self.t_full, self.d_full, self.rig, model)
        self.hc = self.hc_full[:: self.q]
        self._evs.clear()

    # ------------------------------------------------------------ the joint problem (wall, closure)
    def split(self, x):
        k = self.k
        return math.exp(x[0]), np.exp(x[1 : 1 + k]), np.exp(x[1 + k : 1 + 2 * k]), from_solver(x[-NV:])

    def flow(self, v) -> np.ndarray:
        return closure_flow(self.t, self.hc, self.rig, v)

    def head_fd(self, x) -> np.ndarray:
        a, J, tau, v = self.split(x)
        return self.vm.head_of(self.vm.impedance(a, J, tau, self.W), self.vm.flow_sums(self.flow(v)))

    def residual(self, x) -> np.ndarray:
        return self.head_fd(x) + self.corr - self.d

    def jacobian(self, x) -> np.ndarray:
        """Finite differences of the impedance (wall) or of the flow's spectrum (closure), one batched
        inverse FFT each."""
        a, J, tau, v = self.split(x)
        h0 = self.head_fd(x)
        sums0 = self.vm.flow_sums(self.flow(v))
        rows_z, rows_s = [], []
        wall = 1 + 2 * self.k
        for i in range(x.size):
            if i >= wall and self.clo[i - wall] >= self.chi[i - wall]:  # held (the coupling): a zero column
                rows_s.append(sums0)
                continue
            xp = np.array(x, dtype=float)
            xp[i] += STEP
            ap, Jp, taup, vp = self.split(xp)
            if i < wall:
                rows_z.append(self.vm.impedance(ap, Jp, taup, self.W))
            else:
                rows_s.append(self.vm.flow_sums(self.flow(vp)))
        hz = self.vm.head_of(np.array(rows_z), sums0)
        hs = self.vm.head_of(self.vm.impedance(a, J, tau, self.W), np.array(rows_s))
        return ((np.vstack([hz, hs]) - h0) / STEP).T

    def refresh(self, a, J, tau, v) -> None:
        """The correction h_MOC - h_FD at this wall and closure (time-domain laws only)."""
        if self.tm.active:
            x = np.concatenate([[math.log(a)], np.log(J), np.log(tau), to_solver(v)])
            self.corr = self.tm.head(a, J, tau, flow=tm_flow(self.t, self.flow(v))) - self.head_fd(x)

    def basins(self) -> np.ndarray:
        """Stage 1: the starts, each taken a few joint steps; the best goes on, with the correction refreshed
        at its optimum (x = wall and closure)."""
        k, m = self.k, self.rig.manoeuvre
        lo = np.concatenate([[math.log(self.a0 * 0.9)], np.full(k, math.log(1e-8)), np.full(k, math.log(1e-4)), self.clo])
        hi = np.concatenate([[math.log(self.a0 * 1.1)], np.full(k, math.log(10.0)), np.full(k, math.log(1e4)), self.chi])
        v0 = to_solver([self.vi.params.get(name, 0.0) for name in PARAM_NAMES])
        starts = [v0] + [to_solver([p.get(name, 0.0) for name in PARAM_NAMES]) for p in self.vi.alternatives]
        starts += [[math.log(m.beta_per_s), v0[1], math.log(power), math.log(share), closure_kappa(self.rig, self.vi), 0.0]
                   for power, share in PROTOTYPES]
        starts += [to_solver(v) for v in own_valve_starts(self.rig)]  # the valve its rig file describes (a table)
        # (a shape held at the rig's valve: the prototypes' shapes clip onto it, and the same start is taken once)
        starts = list({tuple(np.clip(v, self.clo, self.chi)): None for v in starts})
        wall = np.concatenate([[math.log(self.a0)], np.log(self.J0), np.log(self.tau0)])
        # the correction at the first closure, for the comparison of the starts
        self.refresh(self.a0, self.J0, self.tau0, from_solver(np.clip(v0, self.clo, self.chi)))
        self.F0 = sumsq(self.residual(np.clip(np.concatenate([wall, v0]), lo, hi))) / self.d.size
        tries = [levenberg_marquardt(self.residual, self.jacobian, np.clip(np.concatenate([wall, v]), lo, hi), lo, hi,
                                     max_iter=START_ITERATIONS, broyden=BROYDEN) for v in starts]
        ranked = sorted(tries, key=lambda sol: sumsq(sol.fun))
        # the best start and the next that went to another closure both go on (``_refine`` keeps the one the
        # record's own model fits better): on the refinement's grid two closures can fit alike that the fit's grid
        # tells apart (an elastic pipe's imposed sigmoid: power 1 or power on its upper bound with a full tail,
        # 0.007 % apart here and 5.7 in n ln F on the record's first part, taken or not by a start 0.3 mm/s away)
        finalists = [ranked[0]] + [s for s in ranked[1:] if not np.allclose(s.x[-NV:], ranked[0].x[-NV:],
                                                                               atol=FINALIST_ATOL)][:1]
        out = []
        for sol in finalists:
            x = sol.x
            for _ in range(JOINT_PASSES if self.tm.active else 1):
                self.refresh(*self.split(x))
                x = levenberg_marquardt(self.residual, self.jacobian, x, lo, hi, max_iter=JOINT_ITERATIONS,
                                        broyden=BROYDEN).x
            out.append(x)
        return out

    # ------------------------------------------------------------ variable projection
    def evaluator(self, v) -> HeadEvaluator:
        """The frequency model driven by closure v (its linear friction stand-in), kept for the steps."""
        key = np.asarray(v, dtype=float).tobytes()
        ev = self._evs.get(key)
        if ev is None:
            if len(self._evs) > 32:
                self._evs.clear()
            ev = self._evs[key] = HeadEvaluator(self.rig, self.t, band_hz=None, flow=self.flow(from_solver(v)),
                                                extra_impedance=self.eq)
        return ev

    def project(self, x) -> tuple[np.ndarray, LMSolution]:
        """Stage 2 from the joint point x: the closure v and the projected problem's last solution (its
        residual and projected Jacobian, for the standard errors)."""
        pm = ParamMap(self.k, self.bounds)
        a, J, tau, valve = self.split(x)
        v = np.clip(np.asarray(x[-NV:], dtype=float), self.clo, self.chi)
        walls: dict = {}
        best = {"xw": pm.project(pm.pack(a, J, tau)), "F": math.inf}

        def wall_of(v):
            """The wall solved under closure v, from the best wall so far (cached per closure)."""
            key = np.asarray(v, dtype=float).tobytes()
            if key not in walls:
                sol = Stage(self.evaluator(v), self.d - self.corr).lsq(pm, best["xw"], max_nfev=INNER_NFEV, ftol=1e-12)
                walls[key] = sol.x
                if sol.F < best["F"]:
                    best.update(xw=sol.x, F=sol.F)
            return walls[key]

        def residual(v):
            return self.evaluator(v).head(*pm.unpack(wall_of(v))) + self.corr - self.d

        def jacobian(v):
            xw = wall_of(v)
            h0, Jw = self.evaluator(v).head_jac_x(*pm.unpack(xw))
            cols = []
            for i in range(NV):
                if self.clo[i] >= self.chi[i]:  # held (the coupling: the rig's valve law): a zero column
                    cols.append(np.zeros_like(h0))
                    continue
                vp = np.array(v, dtype=float)
                step = STEP if vp[i] + STEP <= self.chi[i] else -STEP
                vp[i] += step
                cols.append((self.evaluator(vp).head(*pm.unpack(xw)) - h0) / step)
            Jc = np.array(cols)
            # the closure's columns orthogonal to the wall's: what the wall cannot take up when the closure moves
            coef = np.linalg.lstsq(gram(np.ascontiguousarray(Jw)), Jw @ Jc.T, rcond=1e-12)[0]
            return (Jc - coef.T @ Jw).T

        sol = None
        for it in range(PROJECTION_PASSES if self.tm.active else 1):
            if self.tm.active:
                self.refresh(*pm.unpack(best["xw"] if it else pm.project(pm.pack(a, J, tau))), from_solver(v))
                walls.clear()
                best["F"] = math.inf
            sol = levenberg_marquardt(residual, jacobian, v, self.clo, self.chi, max_iter=PROJECTION_ITERATIONS,
                                      ftol=PROJECTION_GAIN / self.d.size)
            v = sol.x
        return v, LMSolution(sol.x, sol.fun, jacobian(sol.x), sol.iterations), pm.unpack(wall_of(v))

    # ------------------------------------------------------------ the record's model on the fit's own grid
    def full_head(self, wall, v) -> np.ndarray:
        """The record's model (the time-domain model with a nonlinear friction, else the full-band frequency model)
        at ``wall`` = (a, J', tau) under closure v, on the fit's own grid (not decimated)."""
        q = closure_flow(self.t_full, self.hc_full, self.rig, from_solver(v))
        if self.tm_full is None:
            self.tm_full = TimeDomainModel(self.rig, self.t_full)
            self.vm_full = None if self.tm_full.active else ValveHeadModel(self.rig, self.t_full, band_hz=None, flow=q)
        if self.tm_full.active:
            return self.tm_full.head(*wall, flow=tm_flow(self.t_full, q))
        vm = self.vm_full
        return vm.head_of(vm.impedance(*wall), vm.flow_sums(q))

    def polish(self, wall, v):
        """(wall, closure) polished jointly on the record's model on the fit's own grid (``full_head``):
        Levenberg-Marquardt with a finite-difference Jacobian (one model run per parameter, carried by Broyden's
        update). The projection runs on the record low-passed and decimated (an ideal low-pass: it rings at every
        front of the head's 0.4 % step at the trigger, which the model on the coarse grid does not) with a linear
        friction stand-in and a correction frozen between its stages; its optimum is near, not at, the fit's: an
        elastic pipe's closure (80 m, 420 m/s, the imposed sigmoid, held at its exact family) came out at beta
        32.023 +- 0.005 1/s for the true 32.000, the elastic wall 16 in n ln F short of its fit under the true
        flow, and a fast element took up the difference (S1 named by 11 AIC units; docs/fitting.md, "A valve its
        rig file does not describe"). On the noiseless record the decimated objective's minimum is at 32.02, the
        fit grid's at 32.000."""
        if not POLISH_ITERATIONS:
            return wall, v
        pm = ParamMap(self.k, self.bounds)
        wlo, whi = pm.bounds()
        lo, hi = np.concatenate([wlo, self.clo]), np.concatenate([whi, self.chi])
        nw = pm.size
        x0 = np.clip(np.concatenate([pm.pack(*wall), np.asarray(v, dtype=float)]), lo, hi)

        def residual(x):
            return self.full_head(pm.unpack(x[:nw]), x[nw:]) - self.d_full

        def jacobian(x):
            r0 = residual(x)
            cols = []
            for i in range(x.size):
                if lo[i] >= hi[i]:
                    cols.append(np.zeros_like(r0))
                    continue
                xp = np.array(x, dtype=float)
                step = POLISH_STEP if xp[i] + POLISH_STEP <= hi[i] else -POLISH_STEP
                xp[i] += step
                cols.append((residual(xp) - r0) / step)
            return np.array(cols).T

        sol = levenberg_marquardt(residual, jacobian, x0, lo, hi, max_iter=POLISH_ITERATIONS,
                                  ftol=PROJECTION_GAIN / self.d_full.size, broyden=True, predicted=True)
        if not sumsq(sol.fun) < sumsq(residual(x0)):
            return wall, v
        return pm.unpack(sol.x[:nw]), np.asarray(sol.x[nw:], dtype=float)

    # ------------------------------------------------------------ the check
    @property
    def v0(self) -> np.ndarray:
        return np.clip(to_solver([self.vi.params.get(name, 0.0) for name in PARAM_NAMES]), self.clo, self.chi)

    def start_wall(self):
        return self.a0, self.J0, self.tau0

    def model_F(self, wall, v) -> float:
        """F of the record's model (the time-domain model with a nonlinear friction) at ``wall`` = (a, J', tau)
        under closure v, on the fit's own grid (``full_head``: the objective ``polish`` minimises)."""
        return sumsq(self.full_head(wall, v) - self.d_full) / self.d_full.size
