"""Calibrated parameters, their feasible box, and where the box comes from.

Variables of the optimiser: x = (ln a, ln J'_1..J'_m, ln tau_1..tau_m) for a full Sm,
x = (ln a, ln J'_1..J'_m) for a reduced one (tau_k fixed). J'_k = J_k a^2 rho alpha D / e
is the element's creep compliance relative to the spring's (its share of phi(0)).

Why these variables. The paper bounds E_k and eta_k to [1e6, 1e12]; on the reference rig
E_k <= 1e12 Pa means J'_k >= 1.8e-3, an element that always creeps about 0.2 % of the
spring's compliance, which a 0.1 m noise record sees: no Sm could contain EL or S(m-1),
and on an elastic pipe every element made the fit worse. Here the lower compliance bound
J'_min = 1e-15 is far below anything a record can detect (its head is ~1e-14 m), so an
element can vanish, and S(m-1) plus a vanished element reproduces S(m-1) to a relative
~1e-12 in F. The box is a plain box in x (no coupled E-eta constraint).

The retardation-time bounds come from the data and the rig (:func:`derive_bounds`); the
user can override them (API, ``velab fit --tau-min/--tau-max``, the rig's ``[fit]`` table).
Every fit reports the parameters that end on a bound (:func:`bound_hits`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from velab.rig import Rig
from velab.errors import DataError

# Relative creep compliance J'_k: the lower bound is far below detection (an element at it
# contributes ~1e-14 m of head: F moves by a relative 1e-12 or so), the upper one a wall whose
# creep is 1000 x the spring's.
J_REL_MIN = 1e-15
J_REL_MAX = 1e3
# Default retardation-time range (see derive_bounds)
TAU_MIN_SAMPLES = 2.0  # tau >= 2 sampling steps
TAU_MIN_CLOSURE = 0.1  # tau >= a tenth of the valve's closure time
TAU_MAX_WINDOWS = 10.0  # tau <= 10 windows
WAVE_SPEED_FACTOR = 3.0  # a within [a_nom / 3, 3 a_nom]
# CLI option that moves each bound (named in the report when a parameter ends on it)
BOUND_OPTIONS = {"tau_min_s": "--tau-min", "tau_max_s": "--tau-max"}


def creep_const(rig: Rig) -> float:
    """rho alpha D / e: E0 = c a^2, J'_k = c a^2 J_k."""
    p = rig.pipe
    return p.constraint_alpha * rig.fluid.density_kg_m3 * p.inner_diameter_m / p.wall_thickness_m


@dataclass(frozen=True)
class FitBounds:
    """The feasible box of a calibration (physical units) and where each bound came from."""

    tau_min_s: float
    tau_max_s: float
    wave_speed_min_m_s: float
    wave_speed_max_m_s: float
    J_rel_min: float = J_REL_MIN
    J_rel_max: float = J_REL_MAX
    tau_floor_s: float = 0.0  # the shortest retardation time the sampling resolves (2 steps)
    sources: dict = field(default_factory=dict, compare=False)

    def hint(self, key: str) -> str:
        """The option (with a value to try) that moves bound ``key`` ("tau_min_s"/"tau_max_s")."""
        if key == "tau_min_s":
            if self.tau_floor_s and self.tau_floor_s < self.tau_min_s * 0.999:
                return f"{BOUND_OPTIONS[key]} {self.tau_floor_s:.3g}"
            return BOUND_OPTIONS[key]
        return f"{BOUND_OPTIONS[key]} {10 * self.tau_max_s:.3g}"

    def to_dict(self) -> dict:
        return {
            "tau_min_s": self.tau_min_s, "tau_max_s": self.tau_max_s, "tau_floor_s": self.tau_floor_s,
            "wave_speed_min_m_s": self.wave_speed_min_m_s, "wave_speed_max_m_s": self.wave_speed_max_m_s,
            "J_rel_min": self.J_rel_min, "J_rel_max": self.J_rel_max, "sources": dict(self.sources),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "FitBounds":
        """The bounds of :meth:`to_dict` (a result's ``settings["bounds"]``)."""
        return cls(**{k: d[k] for k in ("tau_min_s", "tau_max_s", "wave_speed_min_m_s", "wave_speed_max_m_s",
                                         "J_rel_min", "J_rel_max", "tau_floor_s")}, sources=dict(d.get("sources", {})))


def _check_tau(value, name: str, where: str) -> float | None:
    if value is None:
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise DataError(f"{where} {name}: must be a number of seconds, got {value!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise DataError(f"{where} {name}: must be a positive number of seconds, got {value!r}")
    return v


def derive_bounds(rig: Rig, dt_s: float, window_s: float, *, tau_min_s=None, tau_max_s=None) -> FitBounds:
    """Bounds for a record sampled every ``dt_s`` over ``window_s`` on ``rig``.

    Precedence for each retardation-time bound: the argument (API or CLI), then the rig's
    ``[fit]`` table (``rig.fit``), then the rule:

    * tau_min = max(2 dt, closure / 10). A retardation time shorter than two samples is not
      sampled at all; one much shorter than the manoeuvre acts as part of the spring (an
      element with tau << 1/omega has phi ~ J' - J' s tau in the manoeuvre's band), so the
      optimiser trades it against a higher wave speed. The closure time is
      ln(81)/beta (90 % -> 10 % of Q0): 13.7 ms on the reference rig.
    * tau_max = 10 x the window. Beyond the window an element creeps linearly,
      J'(1 - exp(-t/tau)) ~ J' t / tau: only J'/tau is seen, tau runs away along the ridge.

    An element of the truth outside the range ends on the bound, and the report says which
    option lifts it.
    """
    fit = getattr(rig, "fit", None)
    sources = {}
    lo = _check_tau(tau_min_s, "tau_min_s", "fit option")
    if lo is not None:
        sources["tau_min_s"] = "option"
    elif fit is not None and getattr(fit, "tau_min_s", None) is not None:
        lo, sources["tau_min_s"] = float(fit.tau_min_s), "rig [fit] table"
    else:
        closure = rig.manoeuvre.closure_time_s
        lo = max(TAU_MIN_SAMPLES * dt_s, TAU_MIN_CLOSURE * closure)
        sources["tau_min_s"] = (f"max({TAU_MIN_SAMPLES:g} x sampling step {dt_s:.4g} s, "
                                f"{TAU_MIN_CLOSURE:g} x closure time {closure:.4g} s)")
    hi = _check_tau(tau_max_s, "tau_max_s", "fit option")
    if hi is not None:
        sources["tau_max_s"] = "option"
    elif fit is not None and getattr(fit, "tau_max_s", None) is not None:
        hi, sources["tau_max_s"] = float(fit.tau_max_s), "rig [fit] table"
    else:
        hi = TAU_MAX_WINDOWS * window_s
        sources["tau_max_s"] = f"{TAU_MAX_WINDOWS:g} x window {window_s:.4g} s"
    if not hi > lo * 1.0001:
        raise DataError(f"retardation-time bounds: tau_min {lo:g} s must be below tau_max {hi:g} s "
                        f"({sources['tau_min_s']}; {sources['tau_max_s']})")
    a = rig.nominal_wave_speed_m_s
    sources["wave_speed"] = f"nominal {a:g} m/s / {WAVE_SPEED_FACTOR:g} .. x {WAVE_SPEED_FACTOR:g}"
    return FitBounds(tau_min_s=lo, tau_max_s=hi, wave_speed_min_m_s=a / WAVE_SPEED_FACTOR,
                     wave_speed_max_m_s=a * WAVE_SPEED_FACTOR, tau_floor_s=TAU_MIN_SAMPLES * dt_s, sources=sources)


@dataclass(frozen=True)
class ParamMap:
    """Maps optimiser variables x to (a, J', tau) within the box of ``bounds``.

    Full Sm: x = (ln a, ln J'_k, ln tau_k). Reduced Sm (fixed tau_k): x = (ln a, ln J'_k).
    """

    m: int
    bounds_: FitBounds
    fixed_tau: tuple[float, ...] | None = None

    @property
    def size(self) -> int:
        return 1 + (self.m if self.fixed_tau else 2 * self.m)

    @property
    def tau_free(self) -> bool:
        return not self.fixed_tau

    def unpack(self, x):
        """(a, J'_k, tau_k) of x."""
        x = np.asarray(x, dtype=float)
        a = math.exp(x[0])
        J = np.exp(x[1 : 1 + self.m])
        tau = np.asarray(self.fixed_tau, dtype=float) if self.fixed_tau else np.exp(x[1 + self.m :])
        return a, J, tau

    def pack(self, a, J_rel, tau=None) -> np.ndarray:
        J = np.maximum(np.asarray(J_rel, dtype=float).reshape(-1), 1e-300)
        parts = [[math.log(a)], np.log(J)]
        if not self.fixed_tau:
            parts.append(np.log(np.asarray(tau if tau is not None else [], dtype=float).reshape(-1)))
        return np.concatenate(parts)

    def bounds(self):
        lo, hi = self._box
        return lo.copy(), hi.copy()

    def bounds_at(self, x):
        """The box (a plain box: independent of x)."""
        return self._box

    @cached_property
    def _box(self):
        b = self.bounds_
        lo = [math.log(b.wave_speed_min_m_s)] + [math.log(b.J_rel_min)] * self.m
        hi = [math.log(b.wave_speed_max_m_s)] + [math.log(b.J_rel_max)] * self.m
        if not self.fixed_tau:
            lo += [math.log(b.tau_min_s)] * self.m
            hi += [math.log(b.tau_max_s)] * self.m
        return np.array(lo), np.array(hi)

    def project(self, x) -> np.ndarray:
        lo, hi = self._box
        return np.clip(np.asarray(x, dtype=float), lo, hi)

    def clip(self, x) -> np.ndarray:
        """Project strictly inside the box (for starting points); J' may stay at its lower bound."""
        lo, hi = self._box
        span = hi - lo
        x = np.clip(np.asarray(x, dtype=float), lo + 1e-6 * span, hi - 1e-6 * span)
        return x

    def embed(self, other: "ParamMap", x_other, J_new=None, tau_new=None) -> np.ndarray:
        """x of this (larger) model that reproduces ``other``'s solution plus added elements.

        The added elements get compliance ``J_new`` (default: the lower bound, i.e. vanished)
        and retardation times ``tau_new`` (default: spread over the box).
        """
        a, J, tau = other.unpack(x_other)
        extra = self.m - other.m
        if extra < 0:
            raise ValueError("cannot embed a larger model in a smaller one")
        Jn = np.full(extra, self.bounds_.J_rel_min) if J_new is None else np.broadcast_to(J_new, (extra,))
        if self.fixed_tau:
            # reduced models are nested by their fixed tau list: element k keeps tau_k
            return self.pack(a, np.concatenate([J, Jn]))
        if tau_new is None:
            tau_new = np.geomspace(self.bounds_.tau_min_s * 3, self.bounds_.tau_max_s / 30, extra + 2)[1:-1]
        tn = np.broadcast_to(np.asarray(tau_new, dtype=float), (extra,))
        return self.project(self.pack(a, np.concatenate([J, Jn]), np.concatenate([tau, tn])))


def bound_hits(pm: ParamMap, x, skip_elements=(), order=None, tol: float = 1e-6) -> list[dict]:
    """The parameters of x that sit on a bound of the box (not counting vanished elements).

    One dict per hit: parameter name ("wave_speed", "tau_k", "J_rel_k"; element k counted
    from 1 in the order ``order`` (indices of x's elements, e.g. sorted by tau), else in
    x's order), which bound, its value, and the option that moves it (if any).
    """
    x = np.asarray(x, dtype=float)
    rank = {int(k): i for i, k in enumerate(order)} if order is not None else {k: k for k in range(pm.m)}
    lo, hi = pm.bounds()
    b = pm.bounds_
    out = []
    m = pm.m

    def hit(i):
        span = hi[i] - lo[i]
        if x[i] <= lo[i] + tol * span:
            return "lower"
        if x[i] >= hi[i] - tol * span:
            return "upper"
        return None

    side = hit(0)
    if side:
        out.append({"parameter": "wave_speed", "bound": side, "value": math.exp(x[0]),
                    "limit": b.wave_speed_min_m_s if side == "lower" else b.wave_speed_max_m_s, "option": None})
    for k in range(m):
        if k in skip_elements:
            continue
        if hit(1 + k) == "upper":
            out.append({"parameter": f"J_rel_{rank[k] + 1}", "bound": "upper", "value": math.exp(x[1 + k]),
                        "limit": b.J_rel_max, "option": None})
        if pm.tau_free:
            side = hit(1 + m + k)
            if side:
                key = "tau_min_s" if side == "lower" else "tau_max_s"
                out.append({"parameter": f"tau_{rank[k] + 1}", "bound": side, "value": math.exp(x[1 + m + k]),
                            "limit": getattr(b, key), "option": BOUND_OPTIONS[key], "hint": b.hint(key)})
    return out
