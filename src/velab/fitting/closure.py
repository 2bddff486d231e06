"""The closure law: the effective opening of a valve closing along a sigmoid in position, and its parameters.

    Q / Q0 = T(sigmoid(beta (t - t_half))) * c(t)^kappa,   T(x) = 1 / sqrt((1 - s) + s x^(-2 n))

beta, t_half: the actuator's sigmoid in position; n: the characteristic's power (phi = x^n; a rig's table is
blended in by ``tail``); s: the valve's share of the steady loss; kappa: how much of the orifice coupling
c(t) = sqrt((Hv0 + h(t)) / Hv0) acts, which the rig's valve law states (``coupling_exponent``) and is not
fitted. The family holds a real butterfly (n = 2, s = 0.05, kappa = 1) and the paper's imposed sigmoid flow
(n = 1, s = 1, kappa = 0) exactly. The solver's variables (``to_solver``/``from_solver``) anchor the flow's
half-closure instant; ``closure_bounds`` is their box.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from velab.rig import Rig


PARAM_NAMES = ("beta_per_s", "t_half_s", "power", "loss_share", "coupling", "tail")


NV = len(PARAM_NAMES)


COUPLING = PARAM_NAMES.index("coupling")


FITTED = NV - 1  # the closure's fitted parameters: all but the coupling, which the rig's valve law states


T50_MAX_FACTOR = 4.0  # the flow's half-closure instant is sought up to this multiple of the commanded one (+ 1 s)


def sigmoid(u) -> np.ndarray:
    return 0.5 * (1.0 - np.tanh(0.5 * np.asarray(u, dtype=float)))  # 1 / (1 + exp(u)), no overflow


def characteristic(x, power: float, tail: float = 0.0, shape=None) -> np.ndarray:
    """phi(x) = (1 - w) x^n + w g(x): a power law blended with ``shape`` g (``tail`` w): g(x) = x by default
    (a manufacturer's table is often linear near shut where a power law is not), the rig's own table where
    it has one (``tail_shape``)."""
    x = np.asarray(x, dtype=float)
    with np.errstate(divide="ignore", over="ignore", under="ignore", invalid="ignore"):
        xn = np.where(x > 0, np.exp(power * np.log(np.where(x > 0, x, 1.0))), 0.0)
    if not tail:
        return xn
    return (1.0 - tail) * xn + tail * (x if shape is None else shape(x))


def tail_shape(rig: Rig):
    """The closure's blended shape g (``characteristic``): the rig's characteristic when it is a table (a
    function of x = p/100; the family then holds the rig's valve exactly at w = 1), else None (linear)."""
    valve = getattr(rig, "valve", None)
    if valve is None or valve.characteristic != "table":
        return None
    return _table_shape(tuple(valve.position_pct), tuple(valve.flow_ratio))


@lru_cache(maxsize=8)
def _table_shape(position_pct: tuple, flow_ratio: tuple):
    from scipy.interpolate import PchipInterpolator  # monotone, no overshoot: as Valve.flow_ratio_at

    f = PchipInterpolator(np.asarray(position_pct) / 100.0, np.asarray(flow_ratio))
    return lambda x: np.clip(f(np.clip(np.asarray(x, dtype=float), 0.0, 1.0)), 0.0, 1.0)


def own_valve_starts(rig: Rig) -> list[tuple]:
    """[the closure (``PARAM_NAMES``) of the rig's own valve on its commanded sigmoid] for a rig whose
    characteristic is a table (w = 1 on ``tail_shape``, its loss share; the imposed sigmoid if its law says so),
    [] otherwise: the power-law starts hold a power law's basin already (added for every rig, this start took a
    campaign's joint J(0.5 s) from the truth to 2.6 of its standard errors)."""
    if tail_shape(rig) is None:
        return []
    m = rig.manoeuvre
    power, share, tail = rig_shape(rig)
    return [(m.beta_per_s, m.half_closure_s, power, share, coupling_exponent(rig), tail)]


def closure_opening(t, beta: float, t_half: float, power: float, share: float, tail: float = 0.0,
                    shape=None) -> np.ndarray:
    """T(sigmoid(beta (t - t_half))) for t >= 0, 1 before the trigger; T(x) = 1/sqrt((1-s) + s/phi(x)^2)."""
    t = np.asarray(t, dtype=float)
    phi = characteristic(sigmoid(beta * (t - t_half)), power, tail, shape)
    with np.errstate(divide="ignore", over="ignore", under="ignore"):
        inv = np.where(phi > 0, 1.0 / np.where(phi > 0, phi, 1.0) ** 2, np.inf)
        tau = np.where(phi > 0, 1.0 / np.sqrt((1.0 - share) + share * inv), 0.0)
    return np.where(t >= 0, tau, 1.0)


def half_flow_offset(power: float, share: float, tail: float = 0.0) -> float:
    """u50 with T(sigmoid(u50)) = 1/2: the flow is half closed at t50 = t_half + u50 / beta (with the linear
    tail; with a table's (``tail_shape``) t50 stays this coordinate, near the half-flow instant)."""
    return _half_flow_offset(float(power), float(share), float(tail))


@lru_cache(maxsize=4096)  # a pure function the solvers ask again at every point they revisit (from_solver)
def _half_flow_offset(power: float, share: float, tail: float) -> float:
    phi50 = math.sqrt(share / (3.0 + share))
    x50 = phi50 ** (1.0 / power)
    if tail > 0.0:  # (1 - w) x^n + w x = phi50: phi is increasing and convex or concave, Newton from x^n's root
        lo, hi = 0.0, 1.0
        for _ in range(40):
            f = (1.0 - tail) * x50**power + tail * x50 - phi50
            if f > 0:
                hi = x50
            else:
                lo = x50
            df = (1.0 - tail) * power * x50 ** (power - 1.0) + tail
            x_new = x50 - f / df if df > 0 else 0.5 * (lo + hi)
            if not lo < x_new < hi:  # (a Newton step out of the bracket: bisect)
                x_new = 0.5 * (lo + hi)
            if abs(x_new - x50) < 1e-15:
                break
            x50 = x_new
    return math.log(1.0 / x50 - 1.0)


def to_solver(valve) -> list[float]:
    """(beta, t_half, n, s, kappa) -> the solver's (ln beta, t50, ln n, ln s, kappa). The flow's own
    half-closure instant t50 is what the record shows (the Joukowsky head's half-way point); with it
    as a variable instead of the position's t_half, the shape (n, s) no longer drags the timing."""
    beta, t_half, power, share, kappa, tail = valve
    return [math.log(beta), t_half + half_flow_offset(power, share, tail) / beta, math.log(power), math.log(share),
            kappa, tail]


def from_solver(v) -> tuple:
    """Inverse of :func:`to_solver`."""
    beta, power, share = math.exp(v[0]), math.exp(v[2]), math.exp(v[3])
    return beta, v[1] - half_flow_offset(power, share, v[5]) / beta, power, share, v[4], v[5]


def coupling_exponent(rig: Rig) -> float:
    """The fitted closure's kappa, as the rig's valve law states it: 1 for the orifice law (the head rise
    acts on the flow through sqrt((Hv0 + h)/Hv0)), 0 for a flow imposed as such."""
    return 0.0 if rig.valve.law == "imposed" else 1.0


def law_words(rig: Rig, kappa: float) -> str:
    """How a fitted closure's coupling exponent came about, for its text."""
    if kappa == coupling_exponent(rig):
        return "the rig's valve law"
    return ("the flow imposed as such, not the rig's orifice law" if kappa == 0.0 else
            "the orifice law, not the rig's imposed flow") + ": the record's first part shows it"


def closure_kappa(rig: Rig, closure=None) -> float:
    """The coupling exponent a fitted closure holds: ``closure``'s (a ValveInput or its params dict) where it
    has one (``choose_closure`` may have taken the other valve law, ``OTHER_LAW_PRICE``), else the rig's
    (``coupling_exponent``)."""
    params = getattr(closure, "params", closure) or {}
    kappa = params.get("coupling") if isinstance(params, dict) else None
    return coupling_exponent(rig) if kappa is None or not math.isfinite(float(kappa)) else float(kappa)


def closure_bounds(rig: Rig, shape: str = "fitted", kappa: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The box of the closure's solver variables (``to_solver``: ln beta, t_half, ln power, ln loss
    share, coupling, tail): beta within 5x the commanded one, the flow's half-closure instant up to
    T50_MAX_FACTOR x the commanded one (+ 1 s), power 0.3-6, loss share 0.001-1; the coupling held at
    the rig's (``coupling_exponent``: its bounds coincide, so the solvers hold it; ``kappa``: held there instead,
    ``closure_kappa``). ``shape`` "rig": power, loss share and tail held at the rig's valve too (``rig_shape``)."""
    m = rig.manoeuvre
    kappa = coupling_exponent(rig) if kappa is None else float(kappa)
    lo = np.array([math.log(m.beta_per_s / 5), 0.0, math.log(0.3), math.log(1e-3), kappa, 0.0])
    hi = np.array([math.log(m.beta_per_s * 5), T50_MAX_FACTOR * m.half_closure_s + 1.0, math.log(6.0), 0.0, kappa, 1.0])
    if shape == "rig":
        power, share, tail = rig_shape(rig)
        for i, v in ((2, math.log(power)), (3, math.log(share)), (5, tail)):
            lo[i] = hi[i] = v
    return lo, hi


def rig_shape(rig: Rig) -> tuple[float, float, float]:
    """(power, loss share, tail) of the closure family that is the rig's own valve (``closure_opening``): its
    characteristic's power (a table: w = 1 on ``tail_shape``) and loss share; the imposed flow: n = 1, s = 1."""
    valve = rig.valve
    if valve.law == "imposed":
        return 1.0, 1.0, 0.0
    if valve.characteristic == "table":
        return 2.0, float(valve.series_loss_share), 1.0
    return float(valve.power), float(valve.series_loss_share), 0.0
