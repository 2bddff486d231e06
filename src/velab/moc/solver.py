"""Coefficients of the characteristic scheme and :func:`moc_solve` (the solver on its own grid).

See :mod:`velab.moc` for the formulation; the marching itself is the compiled
:func:`velab.moc.kernel.march`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from velab.config import Material
from velab.rig import GRAVITY_M_S2, Rig
from velab.friction import STEADY_LAWS, UNSTEADY_LAWS, weighting_exponentials
from velab.model import creep_scale, flow_perturbation
from velab.moc import kernel
from velab.valvelaw import VALVE_LAWS, commanded_position_pct

FRICTION_LAWS = STEADY_LAWS
_FOLD_DECAY = 36.0  # history terms with n dtau above this decay by exp(-36) = 2e-16 within one step


@dataclass(frozen=True)
class MocResult:
    """Output of :func:`moc_solve`.

    t_s : solver time grid, seconds from the trigger (t_s[0] = 0).
    head_m : head perturbation h(t) just upstream of the valve (m above steady).
    flow_reservoir_m3_s : flow perturbation q(t) leaving the reservoir.
    dt_s : time step actually used (may differ slightly from the requested one).
    wave_speed_m_s : wave speed actually used on the grid.
    n_reaches : number of reaches N (N + 1 nodes).
    friction : steady friction law used (``"quadratic"``, ``"linear"`` or ``"none"``).
    friction_unsteady : unsteady friction used (``"none"``, ``"vardy-brown"``, ``"brunone"``).
    flow_valve_m3_s : flow perturbation q(t) through the valve (imposed, or from the orifice law).
    valve_law : ``"imposed"`` (the sigmoid is the flow) or ``"orifice"`` (the sigmoid is MV's position).
    position_pct : the valve's position, % open, with the orifice law (None with the imposed flow).
    """

    t_s: np.ndarray
    head_m: np.ndarray
    flow_reservoir_m3_s: np.ndarray
    dt_s: float
    wave_speed_m_s: float
    n_reaches: int
    friction: str
    friction_unsteady: str = "none"
    flow_valve_m3_s: np.ndarray | None = None
    valve_law: str = "imposed"
    position_pct: np.ndarray | None = None


def grid(rig: Rig, wave_speed_m_s: float, dt_s: float, adjust: str = "dt") -> tuple[int, float, float]:
    """Characteristic grid (N, dt', a') with L = N a' dt' exactly.

    ``adjust="dt"`` keeps the wave speed and moves dt; ``"wave_speed"`` keeps dt
    and moves the wave speed. N is at least 2 so that the pipe has an interior node.
    """
    if not dt_s > 0:
        raise ValueError(f"dt_s must be positive, got {dt_s}")
    L = rig.pipe.length_m
    n = max(2, int(round(L / (wave_speed_m_s * dt_s))))
    if adjust == "dt":
        return n, L / (n * wave_speed_m_s), wave_speed_m_s
    if adjust == "wave_speed":
        return n, dt_s, L / (n * dt_s)
    raise ValueError(f"adjust must be 'dt' or 'wave_speed', got {adjust!r}")


def check_laws(friction: str, unsteady: str) -> None:
    if friction not in STEADY_LAWS:
        raise ValueError(f"friction must be one of {STEADY_LAWS}, got {friction!r}")
    if unsteady not in UNSTEADY_LAWS:
        raise ValueError(f"unsteady friction must be one of {UNSTEADY_LAWS}, got {unsteady!r}")


def creep_coefficients(J_rel, tau, dt: float):
    """Per-element coefficients of the creep recursion (exact for h linear over a step).

    eps'_new = c_new h_new + c0, c0 = c_old h_old + e eps'_old, e = exp(-dt/tau);
    Sigma = G h_new - sum_k (dt/tau_k) c0_k with G = sum_k J'_k (1 - e_k).
    """
    J_rel = np.ascontiguousarray(J_rel, dtype=float).reshape(-1)
    tau = np.ascontiguousarray(tau, dtype=float).reshape(-1)
    if J_rel.shape != tau.shape:
        raise ValueError(f"J_rel and tau must have the same length, got {J_rel.size} and {tau.size}")
    if np.any(~(tau > 0)) or np.any(~np.isfinite(J_rel)) or np.any(J_rel < 0):
        raise ValueError("retardation times must be positive and creep compliances finite and non-negative")
    one_e = -np.expm1(-dt / tau)  # 1 - e, accurate for tau >> dt
    frac = tau * one_e / dt
    return (J_rel * (frac - (1.0 - one_e)), 1.0 - one_e, J_rel * (1.0 - frac), dt / tau,
            float(np.sum(J_rel * one_e)))


def weighting_coefficients(rig: Rig, dt: float, dx: float):
    """(decay, weight, gain) of the weighting-function history for the kernel.

    y_k <- exp(-n_k dtau) y_k + m_k (1 - exp(-n_k dtau))/(n_k dtau) dq: exact for q
    linear over each step. Terms that die within one step are folded into one
    instantaneous weight. gain = dx 16 nu / (g D^2 A).
    """
    p = rig.pipe
    nu = rig.fluid.kinematic_viscosity_m2_s
    dtau = 4.0 * nu * dt / p.inner_diameter_m**2
    m, n = weighting_exponentials(rig.reynolds)
    x = n * dtau
    weight = m * (-np.expm1(-x)) / x
    fast = x > _FOLD_DECAY
    decay = np.concatenate([np.exp(-x[~fast]), [0.0]])
    weight = np.concatenate([weight[~fast], [weight[fast].sum()]])
    gain = dx * 16.0 * nu / (GRAVITY_M_S2 * p.inner_diameter_m**2 * p.area_m2)
    return decay, weight, gain


_EMPTY = np.zeros(0)
_NO_PROBES = np.zeros(0, dtype=np.int64)


def run(rig: Rig, J_rel, tau, q_valve, n_reach: int, dt: float, a: float,
        friction: str, unsteady: str, *, opening=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(head at the valve, reservoir flow, valve flow): :func:`run_probes` without sections."""
    return run_probes(rig, J_rel, tau, q_valve, n_reach, dt, a, friction, unsteady, opening=opening)[:3]


def run_probes(rig: Rig, J_rel, tau, q_valve, n_reach: int, dt: float, a: float,
               friction: str, unsteady: str, *, opening=None, probes=None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Build the kernel's coefficients and march from the steady state.

    The valve node takes the imposed flow perturbation ``q_valve`` at t_n = n dt, or, with
    ``q_valve=None`` and ``opening`` (the valve pair's effective opening tau at t_n), the orifice law
    Q = Q0 tau sqrt((Hv0 + h)/Hv0) with Hv0 = ``rig.valve_head_m`` (physics.md section 10).
    Returns (head at the valve, reservoir flow, valve flow, heads at the nodes ``probes`` (indices 0..N,
    shape (n_steps, len(probes)))), perturbations at t_n.
    """
    check_laws(friction, unsteady)
    if (q_valve is None) == (opening is None):
        raise ValueError("the valve node needs either an imposed flow or an opening, not both")
    if opening is not None:
        valve = np.ascontiguousarray(opening, dtype=float).reshape(-1)
        if not (np.all(np.isfinite(valve)) and np.all(valve >= 0.0)):
            raise ValueError("the valve's effective opening must be finite and non-negative")
        valve_law, hv0 = kernel.VALVE_ORIFICE, float(rig.valve_head_m)
        if not hv0 > 0:
            raise ValueError(f"the orifice law needs a positive steady head above the discharge, got {hv0:g} m")
    else:
        valve = np.ascontiguousarray(q_valve, dtype=float).reshape(-1)
        valve_law, hv0 = kernel.VALVE_IMPOSED, 0.0
    p = rig.pipe
    A = p.area_m2
    B = a / (GRAVITY_M_S2 * A)
    dx = a * dt
    laminar = rig.laminar
    f = rig.with_changes(friction="linear").friction_factor if friction != "none" else 0.0
    R = rig.with_changes(friction="linear").linear_resistance if friction != "none" else 0.0
    # Poiseuille friction is linear in Q: in laminar flow "quadratic" is the linear law
    steady = {"none": kernel.STEADY_NONE, "linear": kernel.STEADY_LINEAR,
              "quadratic": kernel.STEADY_LINEAR if laminar else kernel.STEADY_QUADRATIC}[friction]
    co, cd, cn, cr, G = creep_coefficients(J_rel, tau, dt)
    J_rel = np.ascontiguousarray(J_rel, dtype=float).reshape(-1)
    if unsteady == "vardy-brown":
        wd, ww, wg = weighting_coefficients(rig, dt, dx)
        mode = kernel.UNSTEADY_WEIGHTING
    else:
        wd, ww, wg = _EMPTY, _EMPTY, 0.0
        mode = kernel.UNSTEADY_BRUNONE if unsteady == "brunone" else kernel.UNSTEADY_NONE
    return kernel.march(int(n_reach), float(B), valve, int(valve_law), hv0, int(steady),
                        float(dx * R), float(dx * f / (2 * GRAVITY_M_S2 * p.inner_diameter_m * A**2)),
                        float(rig.steady_flow_m3_s), co, cd, cn, cr, J_rel, G,
                        int(mode), wd, ww, float(wg), float(rig.brunone_k3 * B),
                        np.ascontiguousarray(_NO_PROBES if probes is None else probes, dtype=np.int64))


def material_creep(rig: Rig, material: Material) -> tuple[np.ndarray, np.ndarray]:
    """(J'_k, tau_k) of a material; J'_k uses the material's a (the spring E0 scales the compliance)."""
    J = np.array([e.J_per_pa for e in material.elements], dtype=float)
    tau = np.array([e.tau_s for e in material.elements], dtype=float)
    return J * creep_scale(rig, material.wave_speed_m_s), tau


def moc_solve(rig: Rig, material: Material, t_end_s: float, dt_s: float = 1e-3, *,
              friction: str | None = None, unsteady: str | None = None, adjust: str = "dt",
              valve: str | None = None) -> MocResult:
    """Integrate the viscoelastic RPV transient from the trigger to ``t_end_s`` on the solver's own grid.

    The flow step the sigmoid has at the trigger sits on the grid's first point, so
    every wave front falls on a grid point (sharp, no interpolation): the form for
    checking the physics. :func:`velab.moc.moc_head` gives the head on any sample grid.

    Parameters
    ----------
    rig : the rig (pipe, fluid, steady flow, manoeuvre, friction laws).
    material : pipe wall (wave speed a from the spring E0, Kelvin-Voigt elements).
    t_end_s : last time (s from the trigger) to compute; the record covers [0, t_end_s].
    dt_s : requested time step; see :func:`grid` for how it is made compatible with dx = a dt.
    friction : ``"quadratic"``, ``"linear"`` (tangent R, as the frequency model) or
        ``"none"``; default the rig's law.
    unsteady : ``"none"``, ``"vardy-brown"`` or ``"brunone"``; default the rig's.
    adjust : ``"dt"`` (default) or ``"wave_speed"``, see :func:`grid`.
    valve : ``"orifice"`` (the actuator moves MV along the rig's sigmoid in position, the flow obeys
        the orifice law of ``rig.valve``) or ``"imposed"`` (the sigmoid is the flow, the paper's
        model); default ``rig.valve.law``.
    """
    friction = rig.friction if friction is None else friction
    unsteady = rig.friction_unsteady if unsteady is None else unsteady
    valve = rig.valve.law if valve is None else valve
    check_laws(friction, unsteady)
    if valve not in VALVE_LAWS:
        raise ValueError(f"valve must be one of {', '.join(VALVE_LAWS)}, got {valve!r}")
    n_reach, dt, a = grid(rig, material.wave_speed_m_s, dt_s, adjust)
    n_steps = int(np.floor(t_end_s / dt + 1e-9)) + 1
    t = np.arange(n_steps) * dt
    J_rel, tau = material_creep(rig, material)
    position = None
    if valve == "orifice":
        m = rig.manoeuvre
        position = commanded_position_pct(t, m.beta_per_s, m.gamma)
        head, q_res, q_val = run(rig, J_rel, tau, None, n_reach, dt, a, friction, unsteady,
                                 opening=rig.valve.opening(position))
    else:
        head, q_res, q_val = run(rig, J_rel, tau, flow_perturbation(t, rig), n_reach, dt, a, friction, unsteady)
    return MocResult(t_s=t, head_m=head, flow_reservoir_m3_s=q_res, dt_s=dt, wave_speed_m_s=a,
                     n_reaches=n_reach, friction=friction, friction_unsteady=unsteady, flow_valve_m3_s=q_val,
                     valve_law=valve, position_pct=position)


def moc_valve_head(rig: Rig, material: Material, t_end_s: float, dt_s: float = 1e-3,
                   friction: str | None = None, adjust: str = "dt", valve: str | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(t, h) at the valve from :func:`moc_solve` on the solver's own grid (step possibly adjusted)."""
    r = moc_solve(rig, material, t_end_s, dt_s, friction=friction, adjust=adjust, valve=valve)
    return r.t_s, r.head_m
