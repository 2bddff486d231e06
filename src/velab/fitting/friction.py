"""The rig's friction law in the calibration model: a defect correction of the frequency model.

The frequency-domain model (velab.model, the fitter's fast inner loop) is linear: it carries
the steady friction as its tangent R = f Q0 / (g D A^2) and any friction term linear in q
(Vardy-Brown unsteady friction) exactly through the series impedance. A real pipe's steady
friction is quadratic, J = f Q|Q| / (2 g D A^2): after the closure the flow swings about zero,
where its slope vanishes, and the tangent over-damps the oscillation (physics.md section 9;
on the reference rig 0.9 m rms over 20 s, nine times a 0.1 m noise).

With ``rig.friction == "quadratic"`` (or an unsteady law the frequency model cannot carry)
the fitted head of a model at parameters p is

    h(p) = h_FD(p) + c(p),     c(p) = h_MOC,rig(p) - h_MOC,linear(p),

the difference of two method-of-characteristics runs at the same parameters, one with the
rig's friction and one with the linear friction the frequency model assumes. c is smooth
and depends weakly on p, so the sweep keeps the frequency model as the inner loop, fits it
to d - c(p_j) and refreshes c at the new optimum until it stops moving
(:class:`FrictionCorrection`, used by velab.fitting.sweep). h_FD + c equals the MOC with the
rig's friction up to the MOC's own discretisation error of the linear part (1-6 mm on the
reference rig), which the frequency model does not have.
"""

from __future__ import annotations

import math
import time

import numpy as np

from velab.config import Rig
from velab.errors import DataError
from velab.friction import STEADY_LAWS, UNSTEADY_LAWS
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


class FrictionCorrection:
    """c(p) = h_MOC,rig(p) - h_MOC,linear(p) on the window's time grid ``t_s``.

    ``active`` is False when the frequency model already is the rig's model (linear or no
    steady friction, an unsteady law it carries exactly); then c = 0 and nothing is run.
    """

    def __init__(self, rig: Rig, t_s):
        self.rig = rig
        self.t = np.asarray(t_s, dtype=float)
        self.steady = steady_law(rig)
        self.unsteady = unsteady_law(rig)
        self.active = self.steady == "quadratic" or self.unsteady not in FD_EXACT_UNSTEADY
        # the linear counterpart carries what the frequency model carries
        self.linear_unsteady = self.unsteady if self.unsteady in FD_EXACT_UNSTEADY else "none"
        self.runs = 0
        self.seconds = 0.0

    def zero(self) -> np.ndarray:
        return np.zeros_like(self.t)

    def at(self, a: float, J_rel, tau) -> np.ndarray:
        if not self.active:
            return self.zero()
        t0 = time.perf_counter()
        J_rel = np.asarray(J_rel, dtype=float)
        tau = np.asarray(tau, dtype=float)
        # the MOC picks its own step (velab.moc.default_dt_s: second order, 1e-4 of the Joukowsky head)
        h_rig = moc_head(self.rig, a, J_rel, tau, self.t, friction=self.steady, unsteady=self.unsteady)
        h_lin = moc_head(self.rig, a, J_rel, tau, self.t, friction="linear", unsteady=self.linear_unsteady)
        self.runs += 2
        self.seconds += time.perf_counter() - t0
        out = np.asarray(h_rig, dtype=float) - np.asarray(h_lin, dtype=float)
        if not np.all(np.isfinite(out)):
            raise DataError(f"friction correction: the time-domain model diverged at a = {a:.4g} m/s")
        return out

    def describe(self) -> str:
        if not self.active:
            if self.steady == "linear":
                return ("linearised steady friction (tangent R = f Q0/(g D A^2)) in the frequency model"
                        + (f", {self.unsteady} unsteady friction" if self.unsteady != "none" else ""))
            return "no steady friction" + (f", {self.unsteady} unsteady friction" if self.unsteady != "none" else "")
        return (f"{self.steady} steady friction{'' if self.unsteady == 'none' else ' + ' + self.unsteady + ' unsteady'}"
                f": frequency model + [MOC({self.steady}) - MOC(linear)] at each model's parameters, refreshed "
                f"until it stops moving ({self.runs} MOC runs, {self.seconds:.2f} s)")


def rms(x: np.ndarray) -> float:
    return math.sqrt(float(np.mean(np.square(x)))) if np.size(x) else 0.0
