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

from velab import moc as _moc
from velab.config import Material, KelvinVoigt, Rig
from velab.errors import DataError
from velab.model import creep_scale

STEADY_LAWS = ("quadratic", "linear", "none")
UNSTEADY_LAWS = ("none", "vardy-brown", "brunone")
# unsteady laws the frequency model carries exactly (linear in q, through the series impedance)
FD_EXACT_UNSTEADY = ("none", "vardy-brown")
# the MOC resolves the pipe with at least this many reaches for the correction
MIN_REACHES = 16


def steady_law(rig: Rig, override: str | None = None) -> str:
    """The steady friction law of a rig: "quadratic", "linear" or "none".

    The rig schema's old value "blasius" (the linearised Blasius friction) means "linear".
    """
    law = override if override is not None else getattr(rig, "friction", "linear")
    law = {"blasius": "linear"}.get(law, law)
    if law not in STEADY_LAWS:
        raise DataError(f"friction law {law!r} unknown (choose from {', '.join(STEADY_LAWS)})")
    return law


def unsteady_law(rig: Rig, override: str | None = None) -> str:
    law = override if override is not None else (getattr(rig, "friction_unsteady", None) or "none")
    if law not in UNSTEADY_LAWS:
        raise DataError(f"unsteady friction law {law!r} unknown (choose from {', '.join(UNSTEADY_LAWS)})")
    return law


def fit_rig(rig: Rig, friction: str | None = None, friction_unsteady: str | None = None) -> Rig:
    """The rig with the fit's friction overrides applied (the rig itself if there are none)."""
    changes = {}
    if friction is not None:
        law = steady_law(rig, friction)
        if law != steady_law(rig):
            changes["friction"] = law
    if friction_unsteady is not None:
        law = unsteady_law(rig, friction_unsteady)
        if law != unsteady_law(rig):
            if not hasattr(rig, "friction_unsteady"):
                raise DataError(f"unsteady friction {law!r}: this velab's rig model has no unsteady friction")
            changes["friction_unsteady"] = law
    return rig.with_changes(**changes) if changes else rig


def _moc_head_fallback(rig: Rig, wave_speed_m_s: float, J_rel, tau_s, t_s, *, friction: str,
                       unsteady: str | None = None, dt_s: float | None = None) -> np.ndarray:
    """Thin adapter over ``velab.moc.moc_solve`` with the signature of ``velab.moc.moc_head``."""
    if unsteady not in (None, "none"):
        raise DataError(f"unsteady friction {unsteady!r} needs velab.moc.moc_head")
    t = np.asarray(t_s, dtype=float)
    dt = float(dt_s if dt_s is not None else t[1] - t[0])
    c = creep_scale(rig, wave_speed_m_s)
    els = tuple(KelvinVoigt.from_creep(float(j) / c, float(tk)) for j, tk in zip(J_rel, tau_s))
    mat = Material(wave_speed_m_s=float(wave_speed_m_s), elements=els)
    r = _moc.moc_solve(rig, mat, max(float(t[-1]), 0.0) + 2 * dt, dt, friction=friction)
    return np.interp(t, r.t_s, r.head_m, left=0.0)


moc_head = getattr(_moc, "moc_head", None) or _moc_head_fallback
# the compiled velab.moc.moc_head picks its own (second-order) step; the fallback's first-order
# solver runs at the sample step, at least MIN_REACHES reaches per pipe
_OWN_STEP = moc_head is not _moc_head_fallback


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
        dt = float(self.t[1] - self.t[0])
        self.dt_moc = None if _OWN_STEP else min(dt, rig.pipe.length_m / (MIN_REACHES * rig.nominal_wave_speed_m_s))
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
        kw = {"dt_s": self.dt_moc}
        h_rig = moc_head(self.rig, a, J_rel, tau, self.t, friction=self.steady,
                         unsteady=None if self.unsteady == "none" else self.unsteady, **kw)
        h_lin = moc_head(self.rig, a, J_rel, tau, self.t, friction="linear",
                         unsteady=None if self.linear_unsteady == "none" else self.linear_unsteady, **kw)
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
