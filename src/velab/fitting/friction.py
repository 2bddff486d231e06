"""The rig's friction law in the calibration model: the time-domain model through the fast one.

The frequency-domain model (velab.model, the fitter's fast inner loop) is linear: it carries
the steady friction as a linear resistance and any friction term linear in q (Vardy-Brown
unsteady friction) exactly through the series impedance. A real pipe's steady friction is
quadratic, J = f Q|Q| / (2 g D A^2): after the closure the flow swings about zero, where its
slope vanishes, and the tangent R = f Q0/(g D A^2) over-damps the oscillation (physics.md
section 9; on the reference rig 0.9 m rms over 20 s, nine times a 0.1 m noise; on the
imperial rig 6 m).

With ``rig.friction == "quadratic"`` (or Brunone's unsteady friction, which has no frequency
form) the head of a model at parameters p is the time-domain model's, h_MOC(p) (velab.moc,
with the rig's laws). The sweep fits it by defect correction (velab.fitting.sweep):

    h(p) = h_FD(p) + c,     c = h_MOC(p_j) - h_FD(p_j),

the frequency model plus the difference of the two models at the current parameters p_j,
refreshed at each new optimum until it stops moving (Anderson-mixed fixed point). At the end
c is evaluated at the final p itself, so the reported F is exactly that of h_MOC(p). The
frequency model's linear resistance is first moved to the value that brings it closest to
the time-domain model (:func:`equivalent_resistance`): with the tangent R the correction was
as sensitive to the parameters as the head itself (|dc/dp| about 0.4 |dh/dp| on the reference
rig) and the refresh converged slowly or not at all on the imperial rig.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass

import numpy as np

from velab.rig import GRAVITY_M_S2, Rig
from velab.errors import DataError
from velab.fitting.bounded import minimize_bounded
from velab.friction import STEADY_LAWS, UNSTEADY_LAWS, unsteady_resistance
from velab.model import ValveHeadModel, creep_scale, valve_head
from velab.moc import moc_head

# unsteady laws the frequency model carries exactly (linear in q, through the series impedance)
FD_EXACT_UNSTEADY = ("none", "vardy-brown")


def steady_law(rig: Rig, override: str | None = None) -> str:
    """The steady friction law of the calibration model: "quadratic", "linear" or "none".

    "blasius", the old name of the linearised Blasius friction, means "linear".
    """
    law = override if override is not None else rig.friction
    law = {"blasius": "linear"}.get(law, law)
    if law not in STEADY_LAWS:
        raise DataError(f"friction law {law!r} unknown (choose from {', '.join(STEADY_LAWS)})")
    return law


def unsteady_law(rig: Rig, override: str | None = None) -> str:
    law = override if override is not None else (rig.friction_unsteady or "none")
    if law not in UNSTEADY_LAWS:
        raise DataError(f"unsteady friction law {law!r} unknown (choose from {', '.join(UNSTEADY_LAWS)})")
    return law


def fit_rig(rig: Rig, friction: str | None = None, friction_unsteady: str | None = None) -> Rig:
    """The rig with the fit's friction overrides applied (the rig itself if there are none)."""
    changes = {}
    if friction is not None and steady_law(rig, friction) != rig.friction:
        changes["friction"] = steady_law(rig, friction)
    if friction_unsteady is not None and unsteady_law(rig, friction_unsteady) != rig.friction_unsteady:
        changes["friction_unsteady"] = unsteady_law(rig, friction_unsteady)
    return rig.with_changes(**changes) if changes else rig


class TimeDomainModel:
    """The head on the window's grid from the time-domain model with the rig's friction laws.

    ``active`` is False when the frequency model already is the rig's model (linear or no
    steady friction, an unsteady law it carries exactly); then nothing is ever run.
    """

    def __init__(self, rig: Rig, t_s, flow=None):
        self.rig = rig
        self.t = np.asarray(t_s, dtype=float)
        # the flow at the valve on t (velab.fitting.manoeuvre), imposed in the time-domain model as in
        # the frequency one; None: the rig's sigmoid
        self.flow = None if flow is None else np.asarray(flow, dtype=float)
        self.steady = steady_law(rig)
        self.unsteady = unsteady_law(rig)
        self.active = self.steady == "quadratic" or self.unsteady not in FD_EXACT_UNSTEADY
        self.runs = 0
        self.seconds = 0.0
        self._count_lock = threading.Lock()  # heads run in two threads at once (a polish's Jacobian columns)

    def on_grid(self, t_s) -> "TimeDomainModel":
        """The same laws on another grid (the flow, if any, is given again with ``head(flow=)``)."""
        return TimeDomainModel(self.rig, t_s)

    def flow_of(self):
        """The imposed flow as the MOC takes it (t -> q, linear between the record's samples), or None."""
        if self.flow is None:
            return None
        t, q = self.t, self.flow
        return lambda s: np.interp(s, t, q)

    def head(self, a: float, J_rel, tau, flow=None) -> np.ndarray:
        """h_MOC(p) on the window's grid (the MOC picks its own second-order step, velab.moc); ``flow``
        (t -> q) overrides the model's own flow at the valve."""
        t0 = time.perf_counter()
        h = np.asarray(moc_head(self.rig, a, np.asarray(J_rel, dtype=float), np.asarray(tau, dtype=float), self.t,
                                friction=self.steady, unsteady=self.unsteady,
                                flow=flow if flow is not None else self.flow_of()), dtype=float)
        with self._count_lock:
            self.runs += 1
            self.seconds += time.perf_counter() - t0
        if not np.all(np.isfinite(h)):
            raise DataError(f"friction: the time-domain model diverged at a = {a:.4g} m/s")
        return h

    def describe(self, frictions=()) -> str:
        uns = "" if self.unsteady == "none" else f", {self.unsteady} unsteady friction"
        if not self.active:
            if self.steady == "linear":
                return "linearised steady friction (tangent R = f Q0/(g D A^2)) in the frequency model" + uns
            return "no steady friction" + uns
        fs = [f.factor(self.rig) for f in frictions if math.isfinite(f.factor(self.rig))]
        eq = f"; frequency model's linear resistance {min(fs):.2f}-{max(fs):.2f} x the tangent R" if fs else ""
        ks = [f.kappa for f in frictions if f.kappa]
        if ks:
            eq += f" + {min(ks):.2f}-{max(ks):.2f} x the Vardy-Brown unsteady resistance"
        return (f"{self.steady} steady friction{uns}: each model's head is the time-domain model (MOC) at its "
                f"parameters, fitted through the frequency model plus the correction h_MOC - h_FD, refreshed until "
                f"it stops moving{eq} ({self.runs} MOC runs, {self.seconds:.2f} s)")


@dataclass(frozen=True)
class EquivalentFriction:
    """What the frequency model adds to its series impedance to stand in for a nonlinear friction:
    a change dR of the linear resistance and kappa times the Vardy-Brown unsteady resistance."""

    dR: float = 0.0
    kappa: float = 0.0

    def __call__(self, s, rig: Rig):
        out = np.full(np.shape(s), self.dR, dtype=complex)
        if self.kappa:
            p = rig.pipe
            out += self.kappa * unsteady_resistance(
                s, gravity_area=GRAVITY_M_S2 * p.area_m2, diameter_m=p.inner_diameter_m,
                kinematic_viscosity_m2_s=rig.fluid.kinematic_viscosity_m2_s, reynolds=rig.reynolds)
        return out

    def factor(self, rig: Rig) -> float:
        R = rig.linear_resistance
        return (R + self.dR) / R if R > 0 else math.nan


def equivalent_friction(ev, params, h_time: np.ndarray, unsteady: bool = False) -> EquivalentFriction:
    """The linear friction that brings the frequency model closest to ``h_time`` (least squares).

    The tangent R = f Q0/(g D A^2) is the quadratic law's slope at Q0; after the closure the
    flow swings about zero where that slope vanishes, so the best linear stand-in has a smaller
    R (about 0.3 R on the reference rigs). With ``unsteady`` (Brunone's friction, which has no
    frequency form) a multiple of the Vardy-Brown unsteady resistance is fitted too: both damp
    in proportion to the flow's acceleration. The correction h_MOC - h_FD is then small and
    depends little on the parameters, which is what makes the refresh converge in a few steps.
    ``ev`` is a full-band HeadEvaluator on the window's grid, ``params`` = (a, J', tau).
    """
    R = ev.rig.linear_resistance
    scale = R if R > 0 else 1.0

    def cost(eq):
        return float(np.mean(np.square(ev.fork(eq).head(*params) - h_time)))

    best = EquivalentFriction()
    best_cost = cost(best)
    if R > 0:
        # scipy.optimize.minimize_scalar(method="bounded"), step for step, without importing scipy.optimize
        r = minimize_bounded(lambda v: cost(EquivalentFriction(v * R)), (-1.0, 1.0), xatol=1e-3)
        if r.fun < best_cost:
            best, best_cost = EquivalentFriction(float(r.x) * R), float(r.fun)
    if unsteady:
        from scipy.optimize import minimize  # (buys start-up time: scipy.optimize only for Brunone's friction)

        x0 = np.array([best.dR / scale, 1.0])
        r = minimize(lambda v: cost(EquivalentFriction(v[0] * scale, max(v[1], 0.0))), x0, method="Nelder-Mead",
                     options={"xatol": 1e-3, "fatol": 1e-6 * best_cost, "maxfev": 60})
        if r.fun < best_cost:
            best = EquivalentFriction(float(r.x[0]) * scale, max(float(r.x[1]), 0.0))
    return best


def anderson(xs: list[np.ndarray], gs: list[np.ndarray]) -> np.ndarray:
    """Anderson mixing for the fixed point x = G(x) from the last iterates x_j and G(x_j).

    The friction refresh's plain iteration x <- G(x) converges like an alternating series
    (ratio about -0.5 on the reference rig): mixing the last two or three iterates removes
    that in one or two steps.
    """
    g = gs[-1]
    if len(xs) < 2:
        return g
    f = [gj - xj for xj, gj in zip(xs, gs)]
    dF = np.array([f[i + 1] - f[i] for i in range(len(f) - 1)]).T
    dG = np.array([gs[i + 1] - gs[i] for i in range(len(gs) - 1)]).T
    gamma, *_ = np.linalg.lstsq(dF, f[-1], rcond=1e-10)
    out = g - dG @ gamma
    return out if np.all(np.isfinite(out)) else g


def rms(x: np.ndarray) -> float:
    return math.sqrt(float(np.mean(np.square(x)))) if np.size(x) else 0.0


def fitted_head(t_s, rig: Rig, fit, flow=None) -> np.ndarray:
    """The head of a calibrated model (a ModelFit) on the grid t_s, with the model the fit used:
    the time-domain model for a nonlinear friction law, the full-band frequency model otherwise.
    ``flow``: the flow at the valve on t_s the fit was driven by (velab.fitting.manoeuvre.result_flow;
    None: the rig's sigmoid)."""
    tm = TimeDomainModel(rig, t_s, flow=flow)
    if tm.active:
        a = fit.wave_speed_m_s
        J_rel = np.array([1.0 / e for e in fit.E_pa]) * creep_scale(rig, a)
        return tm.head(a, J_rel, np.array(fit.tau_s))
    if flow is None:
        return valve_head(t_s, rig, fit.material())
    return ValveHeadModel(rig, t_s, band_hz=None, flow=flow).head(fit.material())
