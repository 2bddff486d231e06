"""A straightforward numpy implementation of velab's MOC scheme, the reference for the compiled kernel.

Same equations as :func:`velab.moc.kernel.march` (see :mod:`velab.moc`), written the
obvious way: whole-array numpy operations per time step, new arrays every step, the
two characteristics of every node solved in closed form. It is what the kernel
replaced (about 30x slower), kept only to check the kernel (tests/moc/test_moc.py) and to
time it against (benchmarks/model_eval.py).
"""

from __future__ import annotations

import numpy as np

from velab.rig import GRAVITY_M_S2
from velab.friction import weighting_exponentials


def march_reference(rig, J_rel, tau, q_valve, n_reach, dt, a, friction, unsteady, *, opening=None):
    """(head at the valve, reservoir flow, valve flow) at t_n = n dt; arguments as velab.moc.solver.run
    (``q_valve=None`` and ``opening``: the orifice law at the valve, solved as a quadratic in Q_P)."""
    p = rig.pipe
    A = p.area_m2
    B = a / (GRAVITY_M_S2 * A)
    dx = a * dt
    q0 = rig.steady_flow_m3_s
    lin = rig.with_changes(friction="linear")
    f, R = (0.0, 0.0) if friction == "none" else (lin.friction_factor, lin.linear_resistance)
    k = f / (2 * GRAVITY_M_S2 * p.inner_diameter_m * A**2)
    quadratic = friction == "quadratic" and not rig.laminar
    J_rel = np.asarray(J_rel, dtype=float)[:, None]
    tau = np.asarray(tau, dtype=float)[:, None]
    e = np.exp(-dt / tau)
    G = float(np.sum(J_rel * (1 - e)))

    def friction_at(qn):
        """(a dt J(q), a dt J'(q) / 2) at every node."""
        if quadratic:
            Q = q0 + qn
            return dx * k * (Q * np.abs(Q) - q0**2), dx * k * np.abs(Q)
        return dx * R * qn, np.full(qn.shape, dx * R / 2)

    if unsteady == "vardy-brown":
        nu = rig.fluid.kinematic_viscosity_m2_s
        dtau = 4 * nu * dt / p.inner_diameter_m**2
        m_k, n_k = weighting_exponentials(rig.reynolds)
        x = n_k * dtau
        decay = np.exp(-x)[:, None]
        weight = (m_k * -np.expm1(-x) / x)[:, None]  # no folding: every term kept
        gain = dx * 16 * nu / (GRAVITY_M_S2 * p.inner_diameter_m**2 * A)
        y = np.zeros((m_k.size, n_reach + 1))
    k3B = rig.brunone_k3 * B

    h = np.zeros(n_reach + 1)
    q = np.zeros(n_reach + 1)
    q_old = np.zeros(n_reach + 1)
    eps = np.zeros((J_rel.shape[0], n_reach + 1))
    hv0 = rig.valve_head_m
    head, q_res, q_val = [], [], []
    for n in range(q_valve.size if opening is None else len(opening)):
        # creep: dt * rate at every node (old level), and dt deps/dt at P = G h_P + S
        rate = dt * np.sum((J_rel * h - eps) / tau, axis=0)
        c0 = J_rel * (tau * (1 - e) / dt - e) * h + e * eps
        S = -dt * np.sum(c0 / tau, axis=0)
        adtJ, r = friction_at(q)
        u_p = np.zeros_like(q)
        u_m = np.zeros_like(q)
        if unsteady == "vardy-brown":
            u_p = u_m = gain * y.sum(axis=0)
        elif unsteady == "brunone":
            sgn = np.where(q0 + q >= 0, 1.0, -1.0)
            dqt = q - q_old
            u_p[:-1] = k3B * (dqt[:-1] + sgn[:-1] * np.abs(np.diff(q)))
            u_m[1:] = k3B * (dqt[1:] + sgn[1:] * np.abs(np.diff(q)))
        # characteristics leaving every node j: C+ gives (1 + G/2) h_P + b_j q_P = c1 at node j + 1,
        # C- gives (1 + G/2) h_P - b_j q_P = c2 at node j - 1
        b = B + r
        c1 = h + b * q - adtJ - u_p - rate / 2
        c2 = h - b * q + adtJ + u_m - rate / 2
        c1 = c1[:-1] - S[1:] / 2  # arriving at nodes 1..N
        c2 = c2[1:] - S[:-1] / 2  # arriving at nodes 0..N-1
        h_new = np.zeros_like(h)
        q_new = np.zeros_like(q)
        bp, bm = b[:-2], b[2:]
        q_new[1:-1] = (c1[:-1] - c2[1:]) / (bp + bm)
        h_new[1:-1] = (c1[:-1] - bp * q_new[1:-1]) / (1 + G / 2)
        q_new[0] = -c2[0] / b[1]  # reservoir, h = 0
        if opening is None:
            qv = q_valve[n]  # valve, imposed flow
        else:  # orifice: (Q0 + q)^2 = (Q0 tau)^2 / Hv0 (Hv0 + h), h from C+; numpy's quadratic root
            K2 = (q0 * opening[n]) ** 2 / hv0
            bb = b[-2] / (1 + G / 2)
            D = hv0 + (c1[-1] + b[-2] * q0) / (1 + G / 2)
            roots = np.roots([1.0, K2 * bb, -K2 * D]) if K2 > 0 else np.zeros(1)
            qv = max(0.0, float(np.max(roots.real))) - q0
        q_new[-1] = qv
        h_new[-1] = (c1[-1] - b[-2] * qv) / (1 + G / 2)
        eps = J_rel * (1 - tau * (1 - e) / dt) * h_new + c0
        if unsteady == "vardy-brown":
            y = decay * y + weight * (q_new - q)
        q_old = q
        h, q = h_new, q_new
        head.append(h[-1])
        q_res.append(q[0])
        q_val.append(q[-1])
    return np.array(head), np.array(q_res), np.array(q_val)
