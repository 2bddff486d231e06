"""Numerical core of the calibration: head model with analytic Jacobian, parameter maps.

Everything here is pure numpy/scipy, allocates its own buffers per instance and
mutates no module state, so independent fits can run in parallel threads.

Parameters are optimised in logs, ``x = (ln a, ln E_1..E_m, ln eta_1..eta_m)``, so
that the paper's bounds (E_k, eta_k in [1e6, 1e12]) are a box. In these variables the
wall function of physics.md section 3 reads

    phi(s) = c a^2 sum_k 1 / (E_k + s eta_k),      c = rho alpha D / e,
    Y(s)   = s g A (1/a^2 + c psi(s)),             psi = sum_k 1 / (E_k + s eta_k),

so that every derivative of the impedance Z = -sqrt(W/Y) tanh(L sqrt(W Y)) goes
through dZ/dY = (Zc / 2Y) (tanh g - g sech^2 g), g = L mu. Each Jacobian column
of the head costs one inverse FFT (batched) and one cumulative sum.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft

from velab.config import GRAVITY_M_S2, MODULUS_BOUNDS_PA, VISCOSITY_BOUNDS_PA_S, Rig
from velab.model import ValveHeadModel, creep_scale


class HeadEvaluator:
    """Head perturbation h(t) and its Jacobian for one rig and one time grid.

    ``band_hz`` as in :class:`velab.model.ValveHeadModel`: ``"auto"`` evaluates Z
    only in the manoeuvre's band, ``None`` at every FFT bin (full band).
    """

    def __init__(self, rig: Rig, t_s, *, band_hz="auto"):
        vm = ValveHeadModel(rig, t_s, band_hz=band_hz)
        p = rig.pipe
        self.rig = rig
        self.model = vm
        self.n_t = vm.t.size
        self.s = vm.s_band.copy()
        self.gA = GRAVITY_M_S2 * p.area_m2
        self.W = self.s / self.gA + rig.linear_resistance  # s Li + R
        self.L = p.length_m
        self.c = p.constraint_alpha * rig.fluid.density_kg_m3 * p.inner_diameter_m / p.wall_thickness_m
        self.evaluations = 0
        self.jacobians = 0

    # ---------------------------------------------------------------- core
    def _y(self, a: float, E: np.ndarray, eta: np.ndarray):
        s = self.s
        if E.size:
            terms = 1.0 / (E[:, None] + s[None, :] * eta[:, None])  # (m, nb)
            psi = terms.sum(axis=0)
        else:
            terms = None
            psi = 0.0
        Y = s * self.gA * (1.0 / a**2 + self.c * psi)
        return Y, terms

    def _to_time(self, spectra: np.ndarray) -> np.ndarray:
        """Spectra of head increments (..., nb) -> head series (..., n_t)."""
        return self.model.to_time(spectra)

    def head(self, a: float, E, eta) -> np.ndarray:
        """h(t) for wave speed a (m/s) and KV elements E_k (Pa), eta_k (Pa s)."""
        E = np.asarray(E, dtype=float)
        eta = np.asarray(eta, dtype=float)
        Y, _ = self._y(a, E, eta)
        mu = np.sqrt(Y * self.W)
        Z = -(mu / Y) * np.tanh(mu * self.L)
        self.evaluations += 1
        return self._to_time(Z)

    def head_jac(self, a: float, E, eta):
        """h(t) and dh/d(ln a, ln E_1..m, ln eta_1..m), shape (n_t, 1 + 2m)."""
        E = np.asarray(E, dtype=float)
        eta = np.asarray(eta, dtype=float)
        m = E.size
        s = self.s
        Y, terms = self._y(a, E, eta)
        mu = np.sqrt(Y * self.W)
        g = mu * self.L
        th = np.tanh(g)
        zc = mu / Y
        Z = -zc * th
        dZdY = zc / (2 * Y) * (th - g * (1.0 - th * th))
        cols = np.empty((1 + 2 * m + 1, self.s.size), dtype=complex)
        cols[0] = Z
        cols[1] = dZdY * (s * self.gA * (-2.0 / a**2))
        if m:
            base = dZdY * s * self.gA * self.c
            t2 = terms * terms
            cols[2 : 2 + m] = base * (-E[:, None] * t2)
            cols[2 + m :] = base * (-(s[None, :] * eta[:, None]) * t2)
        out = self._to_time(cols)
        self.evaluations += 1
        self.jacobians += 1
        return out[0], out[1:].T


# ----------------------------------------------------------------- parameter maps

LN_E = (math.log(MODULUS_BOUNDS_PA[0]), math.log(MODULUS_BOUNDS_PA[1]))
LN_ETA = (math.log(VISCOSITY_BOUNDS_PA_S[0]), math.log(VISCOSITY_BOUNDS_PA_S[1]))


@dataclass(frozen=True)
class ParamMap:
    """Maps optimiser variables x to (a, E, eta) and the Jacobian to x.

    Full Sm: x = (ln a, ln E_k, ln tau_k). Reduced Sm (fixed tau_k): x = (ln a, ln E_k).
    Feasible set: E_k and eta_k = E_k tau_k within the paper's bounds, tau_k within
    ``tau_bounds`` (retardation times shorter than the data resolve only alias the
    spring), ln a within ``ln_a_bounds``. :meth:`bounds_at` gives the box at x (the
    tau bounds depend on E through the eta bounds), :meth:`project` maps into it.
    """

    m: int
    fixed_tau: tuple[float, ...] | None = None
    ln_a_bounds: tuple[float, float] = (math.log(50.0), math.log(5000.0))
    tau_bounds: tuple[float, float] = (1e-6, 1e6)

    @property
    def size(self) -> int:
        return 1 + (self.m if self.fixed_tau else 2 * self.m)

    def unpack(self, x):
        x = np.asarray(x, dtype=float)
        a = math.exp(x[0])
        E = np.exp(x[1 : 1 + self.m])
        tau = np.asarray(self.fixed_tau) if self.fixed_tau else np.exp(x[1 + self.m :])
        return a, E, E * tau

    def pack(self, a, E, eta) -> np.ndarray:
        E = np.asarray(E, dtype=float)
        parts = [[math.log(a)], np.log(E)]
        if not self.fixed_tau:
            parts.append(np.log(np.asarray(eta, dtype=float) / E))
        return np.concatenate(parts)

    def jac(self, Jfull: np.ndarray) -> np.ndarray:
        """Columns d/d(ln a, ln E|eta, ln eta|E) -> d/d(ln a, ln E|tau, ln tau|E)."""
        m = self.m
        dE = Jfull[:, 1 : 1 + m] + Jfull[:, 1 + m :]
        if self.fixed_tau:
            return np.concatenate([Jfull[:, :1], dE], axis=1)
        return np.concatenate([Jfull[:, :1], dE, Jfull[:, 1 + m :]], axis=1)

    def bounds(self):
        """The outer box (independent of x)."""
        lo = [self.ln_a_bounds[0]]
        hi = [self.ln_a_bounds[1]]
        if self.fixed_tau:
            for tau in self.fixed_tau:
                lt = math.log(tau)
                lo.append(max(LN_E[0], LN_ETA[0] - lt))
                hi.append(min(LN_E[1], LN_ETA[1] - lt))
        else:
            lt = (math.log(self.tau_bounds[0]), math.log(self.tau_bounds[1]))
            lo += [max(LN_E[0], LN_ETA[0] - lt[1])] * self.m + [max(lt[0], LN_ETA[0] - LN_E[1])] * self.m
            hi += [min(LN_E[1], LN_ETA[1] - lt[0])] * self.m + [min(lt[1], LN_ETA[1] - LN_E[0])] * self.m
        return np.array(lo), np.array(hi)

    def bounds_at(self, x):
        lo, hi = self.bounds()
        if not self.fixed_tau and self.m:
            m = self.m
            lnE = np.asarray(x, dtype=float)[1 : 1 + m]
            lo[1 + m :] = np.maximum(lo[1 + m :], LN_ETA[0] - lnE)
            hi[1 + m :] = np.minimum(hi[1 + m :], LN_ETA[1] - lnE)
        return lo, hi

    def project(self, x) -> np.ndarray:
        x = np.asarray(x, dtype=float).copy()
        lo, hi = self.bounds()
        x = np.clip(x, lo, hi)
        lo, hi = self.bounds_at(x)
        return np.clip(x, lo, hi)

    def clip(self, x) -> np.ndarray:
        """Project strictly inside the box (for starting points)."""
        x = self.project(x)
        lo, hi = self.bounds_at(x)
        span = np.maximum(hi - lo, 0)
        return np.clip(x, lo + 1e-6 * span, hi - 1e-6 * span)


def E_from_J_rel(rig: Rig, a: float, J_rel) -> np.ndarray:
    """E_k from the dimensionless J'_k = J_k a^2 rho alpha D / e (depends on a)."""
    return creep_scale(rig, a) / np.asarray(J_rel, dtype=float)
