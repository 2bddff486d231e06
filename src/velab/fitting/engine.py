"""Numerical core of the calibration: head model with analytic Jacobian, parameter maps.

Everything here is pure numpy, keeps its work buffers per instance and mutates no
module state, so independent fits (each with its own evaluators) can run in parallel
threads; one evaluator must not be used by two threads at once (see ``fork``).

Parameters are optimised in logs, ``x = (ln a, ln E_1..E_m, ln eta_1..eta_m)``, so
that the paper's bounds (E_k, eta_k in [1e6, 1e12]) are a box. In these variables the
wall function of physics.md section 3 reads

    phi(s) = c a^2 sum_k 1 / (E_k + s eta_k),      c = rho alpha D / e,
    Y(s)   = s g A (1/a^2 + c psi(s)),             psi = sum_k 1 / (E_k + s eta_k),

so that every derivative of the impedance Z = -sqrt(W/Y) tanh(L sqrt(W Y)) goes
through dZ/dY = (Zc / 2Y) (tanh g - g sech^2 g), g = L mu. Each Jacobian column
of the head costs one inverse FFT (batched); the cumulative sum of the increments is
done in the frequency domain (``ValveHeadModel.sums_to_time``).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from velab.config import GRAVITY_M_S2, MODULUS_BOUNDS_PA, VISCOSITY_BOUNDS_PA_S, Rig
from velab.model import ValveHeadModel, creep_scale, series_impedance


class HeadEvaluator:
    """Head perturbation h(t) and its Jacobian for one rig and one time grid.

    ``band_hz`` as in :class:`velab.model.ValveHeadModel`: ``"auto"`` evaluates Z
    only in the manoeuvre's band, ``None`` at every FFT bin (full band).

    The per-bin factors that do not depend on the parameters (s gA, s Li + R, the flow
    spectrum with the frequency-domain cumulative sum) are computed once. An evaluation
    writes Z and the Jacobian columns straight into one half-spectrum buffer that is
    inverse-transformed in one batched call (``ValveHeadModel.sums_to_time``).

    Work buffers are kept per instance and reused (allocating megabyte arrays on every
    evaluation costs more than the arithmetic): an instance must not be used by two
    threads at once. :meth:`fork` gives a worker thread its own instance on the same
    read-only model. Returned arrays are fresh unless ``out`` is passed.
    """

    _WORK_SLOTS = 4

    def __init__(self, rig: Rig, t_s=None, *, band_hz="auto", _model: ValveHeadModel | None = None):
        vm = _model if _model is not None else ValveHeadModel(rig, t_s, band_hz=band_hz)
        p = rig.pipe
        self.rig = rig
        self.model = vm
        self.n_t = vm.t.size
        self.s = vm.s_band.copy()
        self.gA = GRAVITY_M_S2 * p.area_m2
        self.W = series_impedance(self.s, rig)  # s Li + R (+ unsteady R_u(s)), velab.model
        self.L = p.length_m
        self.c = p.constraint_alpha * rig.fluid.density_kg_m3 * p.inner_diameter_m / p.wall_thickness_m
        self._sgA = self.s * self.gA
        self._sigma = float(vm.sigma)
        self._omega = self.s.imag.copy()
        self._nb = self.s.size
        self._nspec = vm.spec.size
        self._mq = -vm.spec_sum  # -(flow-increment spectrum) / (exp(s dt) - 1)
        self._sgAq2 = self._sgA * vm.spec_sum / 2.0
        self._work: OrderedDict = OrderedDict()
        self.evaluations = 0
        self.jacobians = 0

    def fork(self) -> "HeadEvaluator":
        """Same model and grid, own counters and buffers (for a worker thread)."""
        return HeadEvaluator(self.rig, _model=self.model)

    # ---------------------------------------------------------------- core
    def _buffers(self, m: int, rows: int) -> dict:
        key = (m, rows)
        ws = self._work.get(key)
        if ws is None:
            nb = self._nb
            ws = {"im": np.empty((m, nb)), "den": np.empty((m, nb)), "terms": np.empty((m, nb), dtype=complex),
                  "buf": np.zeros((rows, self._nspec), dtype=complex), "w": np.empty((rows, self.model.n_fft))}
            for name in ("psi", "Y", "mu", "g", "th", "zc", "u"):
                ws[name] = np.empty(nb, dtype=complex)
            self._work[key] = ws
            while len(self._work) > self._WORK_SLOTS:
                self._work.popitem(last=False)
        else:
            self._work.move_to_end(key)
        return ws

    def _eval(self, a: float, E: np.ndarray, eta: np.ndarray, jac: bool, tau_free: bool,
              out: np.ndarray | None = None) -> np.ndarray:
        """Rows: h, then (if jac) dh/d ln a, dh/d ln E_k (tau fixed), [dh/d ln tau_k (E fixed)]."""
        m = E.size
        rows = 1 + (1 + m + (m if tau_free else 0) if jac else 0)
        ws = self._buffers(m, rows)
        Y = ws["Y"]
        if m:
            # t_k = 1/(E_k + s eta_k), s = sigma + i omega, in real arithmetic into kept buffers
            # (no complex temporaries); psi = sum_k t_k; Y = s gA (1/a^2 + c psi)
            re = E + self._sigma * eta
            im, den, terms = ws["im"], ws["den"], ws["terms"]
            np.multiply(self._omega[None, :], eta[:, None], out=im)
            np.multiply(im, im, out=den)
            den += (re * re)[:, None]
            np.divide(re[:, None], den, out=terms.real)
            np.divide(im, den, out=terms.imag)
            np.negative(terms.imag, out=terms.imag)
            psi = ws["psi"]
            if m == 1:
                np.copyto(psi, terms[0])
            else:
                np.sum(terms, axis=0, out=psi)
            np.multiply(psi, self.c, out=Y)
            Y += 1.0 / a**2
            Y *= self._sgA
        else:
            terms = None
            np.multiply(self._sgA, 1.0 / a**2, out=Y)
        mu, g, th, zc = ws["mu"], ws["g"], ws["th"], ws["zc"]
        np.multiply(Y, self.W, out=mu)
        np.sqrt(mu, out=mu)
        np.multiply(mu, self.L, out=g)
        np.tanh(g, out=th)
        np.divide(mu, Y, out=zc)  # Zc
        b = ws["buf"][:, : self._nb]
        np.multiply(zc, th, out=b[0])
        b[0] *= self._mq  # Z = -Zc tanh(mu L), times the summed flow spectrum
        if jac:
            # dZ/dY = (Zc / 2Y) (tanh g - g sech^2 g); dY/d ln a = -2 s gA / a^2;
            # dY/d ln E_k|tau = -s gA c t_k; dY/d ln tau_k|E = -s gA c s eta_k t_k^2
            u = ws["u"]
            np.multiply(th, th, out=u)
            np.subtract(1.0, u, out=u)
            u *= g
            np.subtract(th, u, out=u)
            P = zc
            P /= Y
            P *= u
            P *= self._sgAq2  # dZ/dY s gA q
            np.multiply(P, -2.0 / a**2, out=b[1])
            if m:
                P *= -self.c
                cE = b[2 : 2 + m]
                np.multiply(terms, P, out=cE)
                if tau_free:
                    ct = b[2 + m :]
                    np.multiply(self.s[None, :], eta[:, None], out=ct)
                    ct *= terms
                    ct *= cE
        self.evaluations += 1
        if jac:
            self.jacobians += 1
        return self.model.sums_to_time(ws["buf"], out=out, work=ws["w"])

    def head(self, a: float, E, eta, out: np.ndarray | None = None) -> np.ndarray:
        """h(t) for wave speed a (m/s) and KV elements E_k (Pa), eta_k (Pa s)."""
        o = None if out is None else out.reshape(1, -1)
        return self._eval(a, np.asarray(E, dtype=float), np.asarray(eta, dtype=float), False, False, o)[0]

    def head_jac_x(self, a: float, E, eta, tau_free: bool = True, out: np.ndarray | None = None):
        """h(t) and the Jacobian rows in the optimiser's variables, shape (k, n_t), C-ordered:
        d/d ln a, d/d ln E_k (tau fixed), and d/d ln tau_k (E fixed) if ``tau_free``.
        ``out`` (1 + k, n_t) is filled if given."""
        res = self._eval(a, np.asarray(E, dtype=float), np.asarray(eta, dtype=float), True, tau_free, out)
        return res[0], res[1:]

    def head_jac(self, a: float, E, eta):
        """h(t) and dh/d(ln a, ln E_1..m, ln eta_1..m), shape (n_t, 1 + 2m)."""
        E = np.asarray(E, dtype=float)
        m = E.size
        h, Jx = self.head_jac_x(a, E, eta, True)
        # d/d ln E|eta = d/d ln E|tau - d/d ln tau|E;  d/d ln eta|E = d/d ln tau|E
        Jf = Jx.copy()
        Jf[1 : 1 + m] -= Jx[1 + m :]
        return h, Jf.T


# ----------------------------------------------------------------- reductions

# Sums over the n samples are done in blocks small enough that OpenBLAS never splits
# them over threads: a threaded dot product sums in a different order, so F would
# depend (in the last bits) on the machine's core count and on what else is running;
# the blocks are added in a fixed order. Measured: no slower than one threaded call.
_BLOCK = 1024


def sumsq(r: np.ndarray) -> float:
    """sum(r**2), summed in fixed blocks (bit-reproducible whatever the BLAS threading)."""
    return dot(r, r)


def dot(u: np.ndarray, v: np.ndarray) -> float:
    """u . v for 1-D arrays, summed in fixed blocks."""
    n = u.shape[-1]
    if n <= _BLOCK:
        return float(np.dot(u, v))
    return float(sum(np.dot(u[i : i + _BLOCK], v[i : i + _BLOCK]) for i in range(0, n, _BLOCK)))


def gram(B: np.ndarray) -> np.ndarray:
    """B B^T for B of shape (rows, n), rows small, summed over n in fixed blocks."""
    n = B.shape[1]
    M = B[:, :_BLOCK] @ B[:, :_BLOCK].T
    for i in range(_BLOCK, n, _BLOCK):
        b = B[:, i : i + _BLOCK]
        M += b @ b.T
    return M


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
        lo, hi = self._box
        return lo.copy(), hi.copy()

    @cached_property
    def _box(self):
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
