"""The compiled time-marching kernel of the method of characteristics (numba).

One function, :func:`march`, integrates the RPV transient on the characteristic
grid dx = a dt in perturbation variables (h, q about the steady state); the
formulation and the meaning of every coefficient are in :mod:`velab.moc`.
It releases the GIL (fits in parallel threads run in parallel) and is compiled on first use (about 2-4 s) and cached on disk (``cache=True``):
next to this file when the package directory is writable, else in numba's
per-user cache directory (``NUMBA_CACHE_DIR`` overrides both); a cached load
costs about 0.1 s per process.

All array arguments are float64 and contiguous, all integer flags int64, so that
exactly one specialisation is ever compiled (:func:`velab.moc.solver.run` builds them).
"""

from __future__ import annotations

import numpy as np
from numba import njit

# steady friction law (a dt times the change of the friction slope at the foot of a characteristic)
STEADY_NONE, STEADY_LINEAR, STEADY_QUADRATIC = 0, 1, 2
# unsteady friction
UNSTEADY_NONE, UNSTEADY_WEIGHTING, UNSTEADY_BRUNONE = 0, 1, 2
# the valve node: the flow imposed, or the orifice law of the valve pair (physics.md section 10)
VALVE_IMPOSED, VALVE_ORIFICE = 0, 1


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def march(n_reach, B, valve, valve_law, hv0, steady, adt_R, adt_k, q0,
          creep_old, creep_decay, creep_new, creep_rate, creep_J, creep_gain,
          unsteady, wf_decay, wf_weight, wf_gain, k3_B, probes):
    """March n_steps = valve.size steps from the undisturbed state.

    Returns (head at the valve, reservoir flow, valve flow, heads at the nodes ``probes``), perturbations
    at t_n = n dt; the last has shape (n_steps, probes.size) (sections along the pipe, velab.moc.head).

    n_reach : N (N + 1 nodes, node 0 at the reservoir, node N at the valve).
    B : a / (g A).
    valve, valve_law, hv0 : the valve node at t_n = n dt. VALVE_IMPOSED: ``valve`` is the imposed
        flow perturbation q. VALVE_ORIFICE: ``valve`` is the effective opening tau of the valve pair
        and the flow obeys the orifice law (Q0 + q)^2 = (Q0 tau)^2 / Hv0 (Hv0 + h) with C+, hv0 = Hv0
        (m): a quadratic in Q = Q0 + q, its non-negative root; Q = 0 once the head would fall below
        the free discharge (nothing flows back in through a valve discharging to air).
    steady, adt_R, adt_k, q0 : steady friction a dt (J(Q0 + q) - J(Q0)) with its slope
        (linear adt_R q; quadratic adt_k ((Q0 + q)|Q0 + q| - Q0^2)), trapezoidal in time
        with J(q_P) linearised about the foot (semi-implicit, second order).
    creep_* : per Kelvin-Voigt element k (exact recursion for h linear over a step):
        eps_new = creep_new h_new + c0, c0 = creep_old h_old + creep_decay eps_old;
        dt deps/dt at a node = creep_gain h_new + S with S = -sum_k creep_rate c0
        (creep_rate = dt/tau_k); with creep_J = J'_k the rate is (J'_k h - eps_k)/tau_k.
        The creep term of a characteristic is the trapezoidal rule between its foot and P.
    unsteady, wf_*, k3_B : weighting-function history y_k (y = wf_decay y + wf_weight dq,
        term wf_gain sum_k y_k) or Brunone's k3 B (dq_t + sign(Q) |dq_x|); explicit at the foot.
    """
    n_steps = valve.size
    n1 = n_reach + 1
    m = creep_old.size
    kw = wf_decay.size
    h = np.zeros(n1)
    q = np.zeros(n1)
    q_prev = np.zeros(n1)  # q one step earlier (Brunone's dq/dt)
    cp = np.zeros(n1)  # known part of the C+ characteristic leaving node j
    cm = np.zeros(n1)  # ... of the C- characteristic leaving node j
    b = np.full(n1, B)  # B + r_j, r_j = a dt J'(q_j) / 2 (implicit part of the friction)
    rate = np.zeros(n1)  # dt/2 * creep rate at the old time level
    S = np.zeros(n1)  # creep term's known part at the new time level
    c0 = np.zeros((m, n1))
    y = np.zeros((kw, n1))
    U = np.zeros(n1)  # weighting-function friction term wf_gain sum_k y_k at each node
    dq = np.zeros(n1)
    head = np.empty(n_steps)
    probe_head = np.empty((n_steps, probes.size))
    q_res = np.empty(n_steps)
    q_val = np.empty(n_steps)
    half_G1 = 1.0 + 0.5 * creep_gain
    inv_half_G1 = 1.0 / half_G1
    q0sq = q0 * q0
    half_adt_R = 0.5 * adt_R

    for n in range(n_steps):
        # ---- the two characteristics leaving every node (old time level)
        if steady == STEADY_QUADRATIC:
            for j in range(n1):
                Q = q0 + q[j]
                fr = adt_k * (Q * abs(Q) - q0sq)  # a dt J(q_j)
                b[j] = B + adt_k * abs(Q)  # B + a dt J'(q_j) / 2
                cp[j] = h[j] + b[j] * q[j] - fr - rate[j]
                cm[j] = h[j] - b[j] * q[j] + fr - rate[j]
        elif steady == STEADY_LINEAR:
            for j in range(n1):
                fr = adt_R * q[j]
                b[j] = B + half_adt_R
                cp[j] = h[j] + b[j] * q[j] - fr - rate[j]
                cm[j] = h[j] - b[j] * q[j] + fr - rate[j]
        else:
            for j in range(n1):
                cp[j] = h[j] + B * q[j] - rate[j]
                cm[j] = h[j] - B * q[j] - rate[j]
        if unsteady == UNSTEADY_WEIGHTING:
            for j in range(n1):
                cp[j] -= U[j]
                cm[j] += U[j]
        elif unsteady == UNSTEADY_BRUNONE:
            for j in range(n1):
                sgn = 1.0 if q0 + q[j] >= 0.0 else -1.0
                dqt = q[j] - q_prev[j]
                if j < n_reach:  # C+ from j to j+1: the reach it crosses
                    cp[j] -= k3_B * (dqt + sgn * abs(q[j + 1] - q[j]))
                if j > 0:  # C- from j to j-1
                    cm[j] += k3_B * (dqt + sgn * abs(q[j] - q[j - 1]))
                q_prev[j] = q[j]
        # ---- new time level: interior nodes from C+ (i-1) and C- (i+1)
        for i in range(1, n_reach):
            c1 = cp[i - 1] - 0.5 * S[i]
            c2 = cm[i + 1] - 0.5 * S[i]
            bp = b[i - 1]
            bm = b[i + 1]
            qn = (c1 - c2) / (bp + bm)
            q[i] = qn
            h[i] = (c1 - bp * qn) * inv_half_G1
        # reservoir: h = 0 (no creep there), C- gives q; valve: q imposed or from the orifice law, C+ gives h
        h[0] = 0.0
        q[0] = -(cm[1] - 0.5 * S[0]) / b[1]
        c1 = cp[n_reach - 1] - 0.5 * S[n_reach]
        bp = b[n_reach - 1]
        if valve_law == VALVE_ORIFICE:
            # C+: h = (c1 - bp q) / (1 + G/2) = D - Hv0 - bb Q with Q = Q0 + q; orifice: Q^2 = K2 (Hv0 + h)
            K2 = valve[n] * valve[n] * q0sq / hv0
            bb = bp * inv_half_G1
            D = hv0 + (c1 + bp * q0) * inv_half_G1
            if K2 > 0.0 and D > 0.0:
                kb = K2 * bb
                # the positive root of Q^2 + kb Q - K2 D = 0, written without cancellation
                qv = 2.0 * K2 * D / (kb + np.sqrt(kb * kb + 4.0 * K2 * D)) - q0
            else:
                qv = -q0  # shut, or the head below the discharge: no flow
        else:
            qv = valve[n]
        q[n_reach] = qv
        h[n_reach] = (c1 - bp * qv) * inv_half_G1
        # ---- creep state to the new level: eps, its rate, and the next step's S and c0
        if m > 0:
            for j in range(n1):
                rate[j] = 0.0
                S[j] = 0.0
            for k in range(m):
                cn = creep_new[k]
                co = creep_old[k]
                cd = creep_decay[k]
                cr = creep_rate[k]
                ck = 0.5 * creep_rate[k] * creep_J[k]  # dt/2 J'_k / tau_k
                ci = 0.5 * creep_rate[k]  # dt/2 / tau_k
                for j in range(n1):
                    hj = h[j]
                    eps = cn * hj + c0[k, j]
                    rate[j] += ck * hj - ci * eps
                    c = co * hj + cd * eps
                    c0[k, j] = c
                    S[j] -= cr * c
        if unsteady == UNSTEADY_WEIGHTING:
            # q now holds the new level, q_prev the old one; U is the next step's friction term
            for j in range(n1):
                dq[j] = q[j] - q_prev[j]
                q_prev[j] = q[j]
                U[j] = 0.0
            for k in range(kw):
                d = wf_decay[k]
                w = wf_weight[k]
                for j in range(n1):
                    yk = d * y[k, j] + w * dq[j]
                    y[k, j] = yk
                    U[j] += wf_gain * yk
        head[n] = h[n_reach]
        for p in range(probes.size):
            probe_head[n, p] = h[probes[p]]
        q_res[n] = q[0]
        q_val[n] = qv
    return head, q_res, q_val, probe_head


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def resample_cubic(values, dt, t, jump_period):
    """4-point Lagrange interpolation of values[n] = f(n dt) at times 0 <= t <= (size - 4) dt.

    f = 0 before 0. If jump_period > 0, f may jump between n - 1 and n at every multiple
    n of jump_period (wave fronts on the characteristic grid; the value at n is after the
    jump): the stencil is then chosen on one side of the jump, so a front stays sharp.
    """
    out = np.empty(t.size)
    n = values.size
    for p in range(t.size):
        x = t[p] / dt
        xr = np.floor(x + 0.5)
        if abs(x - xr) < 1e-9:  # on a grid point (up to rounding): take its side of a front
            x = xr
        i = int(np.floor(x))
        lo = i - 1  # first point of the stencil
        if jump_period > 0:
            r = i % jump_period
            if r == 0:  # jump at i: t is after it
                lo = i
            elif r == jump_period - 1:  # jump at i + 1: t is before it
                lo = i - 3
            elif r == jump_period - 2:  # jump at i + 2
                lo = i - 2
        f = x - lo  # position within the stencil lo .. lo + 3
        acc = 0.0
        for k in range(4):
            j = lo + k
            v = values[j] if 0 <= j < n else 0.0
            w = 1.0
            for m in range(4):
                if m != k:
                    w *= (f - m) / (k - m)
            acc += w * v
        out[p] = acc
    return out


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def resample_cubic_fronts(values, dt, t, period, phase_a, phase_b):
    """:func:`resample_cubic` of a node's series whose fronts fall at every n >= 1 with n % period equal to
    phase_a or phase_b (a section's node j: the trigger's front passes at N - j and N + j, period 2N).
    The 4-point stencil is taken on t's side of a front; where two fronts are too close for that, the
    2-point (linear) one between them."""
    out = np.empty(t.size)
    n = values.size
    for p in range(t.size):
        x = t[p] / dt
        xr = np.floor(x + 0.5)
        if abs(x - xr) < 1e-9:
            x = xr
        i = int(np.floor(x))
        if _front(i, period, phase_a, phase_b):
            lo = i
        elif _front(i + 1, period, phase_a, phase_b):
            lo = i - 3
        elif _front(i + 2, period, phase_a, phase_b):
            lo = i - 2
        else:
            lo = i - 1
        ok = True
        for j in range(lo + 1, lo + 4):
            if _front(j, period, phase_a, phase_b):
                ok = False
        if not ok:  # fronts on both sides: linear between i and i + 1 (or i's value, a front at i + 1)
            v0 = values[i] if 0 <= i < n else 0.0
            v1 = values[i + 1] if 0 <= i + 1 < n else 0.0
            out[p] = v0 if _front(i + 1, period, phase_a, phase_b) else v0 + (x - i) * (v1 - v0)
            continue
        f = x - lo
        acc = 0.0
        for k in range(4):
            j = lo + k
            v = values[j] if 0 <= j < n else 0.0
            w = 1.0
            for m in range(4):
                if m != k:
                    w *= (f - m) / (k - m)
            acc += w * v
        out[p] = acc
    return out


@njit(cache=True, nogil=True)
def _front(j, period, phase_a, phase_b):
    if j < 1 or period <= 0:
        return False
    r = j % period
    return r == phase_a or r == phase_b
