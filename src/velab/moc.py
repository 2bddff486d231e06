"""Method-of-characteristics (MOC) solver for the RPV rig (physics.md section 6).

This is the *independent check* of the frequency-domain model in
:mod:`velab.model`: it integrates the same physics in the time domain on a fixed
characteristic grid (Covas et al. 2005), so an error in the transfer-matrix
algebra, the FFT convention or the time reconstruction of the frequency model
shows up as a disagreement between the two.

Formulation
-----------
The solver works in *perturbation* variables h = H - H_steady(x) and
q = Q - Q0. The steady state is then exactly h = q = 0 (no start-up transient
from a slightly inconsistent initial profile), and both friction laws enter as
the change of the friction slope from its steady value:

* ``"linear"``: J(q) = R q, with the tangent R = f Q0 / (g D A^2) of
  :attr:`velab.config.Rig.linear_resistance`, i.e. exactly the friction of the
  frequency-domain model;
* ``"quadratic"``: J(q) = f (Q|Q| - Q0^2) / (2 g D A^2), Q = Q0 + q, with the same
  steady Darcy f (the difference from ``"linear"`` is the linearisation error).

Viscoelastic wall: with F = alpha D rho g h / (2e) (hoop-stress change) and the
creep compliances J_k, every Kelvin-Voigt element obeys tau_k de_k/dt + e_k = J_k F.
The code carries e'_k = (2 a^2 / g) e_k, which has units of head and obeys
tau_k de'_k/dt + e'_k = J'_k h with the dimensionless J'_k = J_k a^2 rho alpha D/e of
:func:`velab.model.creep_scale` -- the same J'_k that build phi(s) in the frequency
model. The retarded-strain term of the characteristic equations is then
Sigma = dt * sum_k de'_k/dt at the new node P. The recursion that is exact for h
(hence F) linear over a step makes Sigma = G h_P + S_old, linear in h_P, so every
node is a 2 x 2 linear solve (done in closed form, vectorised over nodes).

Characteristics (B = a / (g A)):

    C+:  h_P - h_A + B (q_P - q_A) + a dt J(q_A) + Sigma_P = 0
    C-:  h_P - h_B - B (q_P - q_B) - a dt J(q_B) + Sigma_P = 0

Friction is explicit (evaluated at the foot of the characteristic, A or B), as
in Covas et al.; at dt = 1 ms on the reference rig the resulting first-order
error is far below the agreement target (see docs/model.md).

Boundaries: the reservoir node keeps h = 0 (so its wall never creeps); the
valve node takes the imposed q(t) = Q(t) - Q0 of the sigmoid, including the
0.41 % step at the trigger (:func:`velab.model.flow_perturbation`).

Grid: dx = a dt exactly, N = round(L / (a dt)) reaches. Because L / (a dt) is
not an integer in general, the *time step* is adjusted to dt' = L / (N a)
(default, ``adjust="dt"``) so that the physics -- the wave speed, hence the
Joukowsky head and the period -- is exactly the requested one; the output grid
is then t_n = n dt' rather than n dt. ``adjust="wave_speed"`` keeps dt and uses
a' = L / (N dt) instead (Covas's choice; it shifts the period by up to
1 / (2N) relative, 0.2 % at dt = 1 ms). On the reference rig at dt = 1 ms,
L / (a dt) = 289.995, so either adjustment is 2e-5 relative.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from velab.config import GRAVITY_M_S2, Material, Rig
from velab.model import creep_scale, flow_perturbation

FRICTION_LAWS = ("linear", "quadratic")


@dataclass(frozen=True)
class MocResult:
    """Output of :func:`moc_solve`.

    t_s : solver time grid, seconds from the trigger (t_s[0] = 0).
    head_m : head perturbation h(t) just upstream of the valve (m above steady).
    flow_reservoir_m3_s : flow perturbation q(t) leaving the reservoir.
    dt_s : time step actually used (may differ slightly from the requested one).
    wave_speed_m_s : wave speed actually used on the grid.
    n_reaches : number of reaches N (N + 1 nodes).
    friction : ``"linear"`` or ``"quadratic"``.
    """

    t_s: np.ndarray
    head_m: np.ndarray
    flow_reservoir_m3_s: np.ndarray
    dt_s: float
    wave_speed_m_s: float
    n_reaches: int
    friction: str


def grid(rig: Rig, wave_speed_m_s: float, dt_s: float, adjust: str = "dt") -> tuple[int, float, float]:
    """Characteristic grid (N, dt', a') with L = N a' dt' exactly.

    ``adjust="dt"`` keeps the wave speed and moves dt; ``"wave_speed"`` keeps dt
    and moves the wave speed. N is at least 2 so that the pipe has an interior node.
    """
    if dt_s <= 0:
        raise ValueError(f"dt_s must be positive, got {dt_s}")
    L = rig.pipe.length_m
    n = max(2, int(round(L / (wave_speed_m_s * dt_s))))
    if adjust == "dt":
        return n, L / (n * wave_speed_m_s), wave_speed_m_s
    if adjust == "wave_speed":
        return n, dt_s, L / (n * dt_s)
    raise ValueError(f"adjust must be 'dt' or 'wave_speed', got {adjust!r}")


def moc_solve(rig: Rig, material: Material, t_end_s: float, dt_s: float = 1e-3, *,
              friction: str = "linear", adjust: str = "dt") -> MocResult:
    """Integrate the viscoelastic RPV transient from the trigger to ``t_end_s``.

    Parameters
    ----------
    rig : the rig (pipe, fluid, steady flow, manoeuvre).
    material : pipe wall (wave speed a from the spring E0, Kelvin-Voigt elements).
    t_end_s : last time (s from the trigger) to compute; the record covers [0, t_end_s].
    dt_s : requested time step; see :func:`grid` for how it is made compatible with dx = a dt.
    friction : ``"linear"`` (tangent R, same as the frequency model) or ``"quadratic"``.
    adjust : ``"dt"`` (default) or ``"wave_speed"``, see :func:`grid`.
    """
    if friction not in FRICTION_LAWS:
        raise ValueError(f"friction must be one of {FRICTION_LAWS}, got {friction!r}")
    n_reach, dt, a = grid(rig, material.wave_speed_m_s, dt_s, adjust)
    n_steps = int(np.floor(t_end_s / dt + 1e-9)) + 1
    t = np.arange(n_steps) * dt

    p = rig.pipe
    A = p.area_m2
    B = a / (GRAVITY_M_S2 * A)
    q0 = rig.steady_flow_m3_s
    f = rig.friction_factor
    R = rig.linear_resistance
    k_quad = f / (2 * GRAVITY_M_S2 * p.inner_diameter_m * A**2)
    adt = a * dt

    # Kelvin-Voigt elements, one row each. J'_k uses the *material's* a (it is
    # the spring E0 that scales the compliance), not a grid-adjusted a'.
    J_rel = np.array([e.J_per_pa for e in material.elements]) * creep_scale(rig, material.wave_speed_m_s)
    tau = np.array([e.tau_s for e in material.elements])
    J_rel = J_rel[:, None]
    tau = tau[:, None]
    e_k = np.exp(-dt / tau)
    # Sigma_P = G h_P + S(h_old, eps_old); G and the coefficient of h_old are constants.
    G = float(np.sum(J_rel * (1 - e_k)))
    c_hold = J_rel * (tau * (1 - e_k) / dt - e_k)  # eps_new = c_hnew h_new + c_hold h_old + e_k eps_old
    c_hnew = J_rel * (1 - tau * (1 - e_k) / dt)
    has_creep = material.m > 0
    one_G = 1.0 + G

    q_valve = flow_perturbation(t, rig)

    def fric(qv):
        """a dt (J(q) - J(0)): the change of the friction head drop over one reach."""
        if friction == "linear":
            return adt * R * qv
        Q = q0 + qv
        return adt * k_quad * (Q * np.abs(Q) - q0 * q0)

    # State at t = -dt: the undisturbed steady state.
    h = np.zeros(n_reach + 1)
    q = np.zeros(n_reach + 1)
    eps = np.zeros((material.m, n_reach + 1))
    head = np.empty(n_steps)
    q_res = np.empty(n_steps)
    h_new = np.empty_like(h)
    q_new = np.empty_like(q)

    for n in range(n_steps):
        fr = fric(q)
        cp = h[:-1] + B * q[:-1] - fr[:-1]  # C+ invariant carried from node i-1 to node i
        cm = h[1:] - B * q[1:] + fr[1:]  # C- invariant carried from node i+1 to node i
        if has_creep:
            # c0_k of the recursion, per element and node; S = -dt sum_k c0_k / tau_k.
            c0 = c_hold * h + e_k * eps
            S = -dt * np.sum(c0 / tau, axis=0)
        else:
            S = np.zeros_like(h)
        # Interior nodes 1..N-1: C+ from i-1, C- from i+1.
        cpi = cp[:-1] - S[1:-1]
        cmi = cm[1:] - S[1:-1]
        h_new[1:-1] = (cpi + cmi) / (2 * one_G)
        q_new[1:-1] = (cpi - cmi) / (2 * B)
        # Reservoir node 0: h = 0 (S = 0 there), C- gives q.
        h_new[0] = 0.0
        q_new[0] = -(cm[0] - S[0]) / B
        # Valve node N: imposed q, C+ gives h.
        q_new[-1] = q_valve[n]
        h_new[-1] = (cp[-1] - S[-1] - B * q_valve[n]) / one_G
        if has_creep:
            eps = c_hnew * h_new + c0
        h, h_new = h_new, h
        q, q_new = q_new, q
        head[n] = h[-1]
        q_res[n] = q[0]

    return MocResult(t_s=t, head_m=head, flow_reservoir_m3_s=q_res, dt_s=dt, wave_speed_m_s=a,
                     n_reaches=n_reach, friction=friction)


def moc_valve_head(rig: Rig, material: Material, t_end_s: float, dt_s: float = 1e-3,
                   friction: str = "linear", adjust: str = "dt") -> tuple[np.ndarray, np.ndarray]:
    """(t, h) at the valve from the MOC solver; a thin wrapper of :func:`moc_solve`.

    t is the solver's own grid (step possibly adjusted, see :func:`grid`);
    interpolate with ``np.interp`` to compare on another grid.
    """
    r = moc_solve(rig, material, t_end_s, dt_s, friction=friction, adjust=adjust)
    return r.t_s, r.head_m
