"""Numerical core of the calibration: head model with analytic Jacobian, sums over samples.

Everything here is pure numpy, keeps its work buffers per instance and mutates no
module state, so independent fits (each with its own evaluators) can run in parallel
threads; one evaluator must not be used by two threads at once (see ``fork``).

The wall is described by the wave speed a (the spring) and, per Kelvin-Voigt element, the
dimensionless creep compliance J'_k = J_k a^2 rho alpha D / e and the retardation time
tau_k (physics.md section 3):

    phi(s) = sum_k J'_k u_k,   u_k = 1 / (1 + s tau_k),
    Y(s)   = (s g A / a^2) (1 + phi(s)),

so that every derivative of the impedance Z = -sqrt(W/Y) tanh(L sqrt(W Y)) goes through
dZ/dY = (Zc / 2Y) (tanh g - g sech^2 g), g = L mu, and in the optimiser's variables
(ln a, ln J'_k, ln tau_k):

    dY/d ln a = -2 Y,   dY/d ln J'_k = (s g A / a^2) J'_k u_k,   dY/d ln tau_k = -(s g A / a^2) J'_k s tau_k u_k^2.

An element with J'_k -> 0 vanishes (its columns vanish with it): that is what lets a
larger model contain the smaller one (see velab.fitting.params). Each Jacobian column of
the head costs one inverse FFT (batched); the cumulative sum of the increments is done in
the frequency domain (``ValveHeadModel.sums_to_time``).
"""

from __future__ import annotations

import numpy as np

from velab.rig import GRAVITY_M_S2, Rig
from velab import complexops
from velab.fitting.parallel import both
from velab.model import ValveHeadModel, series_impedance

# an evaluation with at least this many bins is worth splitting over two threads (``workers=2``):
# the full band of a 20 s, 1 kHz window has 20 251, the coarse grid about 1 300
SPLIT_MIN_BINS = 4096


class HeadEvaluator:
    """Head perturbation h(t) and its Jacobian for one rig and one time grid.

    ``band_hz`` as in :class:`velab.model.ValveHeadModel`: ``"auto"`` evaluates Z
    only in the manoeuvre's band, ``None`` at every FFT bin (full band).

    The per-bin factors that do not depend on the parameters (s gA, the series impedance
    W = s Li + R, the flow spectrum with the frequency-domain cumulative sum) are computed
    once. An evaluation writes Z and the Jacobian columns straight into one half-spectrum
    buffer that is inverse-transformed in one batched call (``ValveHeadModel.sums_to_time``).

    Work buffers are kept per instance and reused (allocating megabyte arrays on every
    evaluation costs more than the arithmetic): an instance must not be used by two
    threads at once. :meth:`fork` gives a worker thread its own instance on the same
    read-only model. Returned arrays are fresh unless ``out`` is passed. ``workers=2`` splits
    an evaluation of at least ``SPLIT_MIN_BINS`` bins in two halves, one on the helper thread
    of velab.fitting.parallel (bit-identical to ``workers=1``).
    """

    _MAX_M = 6  # the work buffers are sized for this many elements (S6) at the first evaluation

    def __init__(self, rig: Rig, t_s=None, *, band_hz="auto", extra_impedance=None, workers: int = 1,
                 flow=None, position_m: float | None = None, _model: ValveHeadModel | None = None):
        # flow: the flow at the valve on t_s (velab.fitting.manoeuvre; None: the rig's sigmoid);
        # position_m: the head at that distance from the reservoir (a section, velab.fitting.sections)
        vm = _model if _model is not None else ValveHeadModel(rig, t_s, band_hz=band_hz, flow=flow,
                                                              position_m=position_m)
        self.position_m = vm.position_m  # None: at the valve
        p = rig.pipe
        self.rig = rig
        self.model = vm
        self.n_t = vm.t.size
        self.s = vm.s_band.copy()
        self.gA = GRAVITY_M_S2 * p.area_m2
        # series impedance per unit length (inertance and friction): the one place it enters;
        # extra_impedance(s, rig) moves the linearised friction (velab.fitting.friction)
        self.extra_impedance = extra_impedance
        self.W = series_impedance(self.s, rig)  # s Li + R (+ unsteady R_u(s)), velab.model
        if extra_impedance is not None:
            self.W = self.W + extra_impedance(self.s, rig)
        self.L = p.length_m
        self._sgA = self.s * self.gA
        self._sigma = float(vm.sigma)
        self._omega = self.s.imag.copy()
        self._nb = self.s.size
        self._nspec = vm.spec.size
        self._mq = -vm.spec_sum  # -(flow-increment spectrum) / (exp(s dt) - 1)
        self._q2 = vm.spec_sum / 2.0
        self._work: dict | None = None
        # 2: large evaluations run in two halves, one on velab.fitting.parallel's helper thread (same result)
        self.workers = workers
        self.evaluations = 0
        self.jacobians = 0

    def fork(self, extra_impedance=False, workers: int | None = None) -> "HeadEvaluator":
        """Same model and grid, own counters and buffers (for a worker thread); optionally another
        linearised friction (``extra_impedance(s, rig)`` added to the series impedance; None: none)
        or another number of ``workers``."""
        extra = self.extra_impedance if extra_impedance is False else extra_impedance
        return HeadEvaluator(self.rig, extra_impedance=extra, workers=self.workers if workers is None else workers,
                             _model=self.model)

    # ---------------------------------------------------------------- core
    def _buffers(self, m: int, rows: int) -> dict:
        """Views of the work buffers for m elements and ``rows`` output rows. Sized once, for the
        largest model (``_MAX_M`` elements and every Jacobian row; one row until a Jacobian is
        asked for), so that memory is bounded and reused whatever sequence of models is evaluated."""
        ws = self._work
        if ws is None or m > ws["m"] or rows > ws["rows"]:
            mm = max(m, self._MAX_M, ws["m"] if ws else 0)
            # with a Jacobian: every row of the largest model at once; head only (a probe, e.g. the
            # friction fit's evaluators, velab.fitting.friction): one row (a 14-row buffer of the full
            # band is 9 MB of fresh pages, more than the evaluation itself)
            rr = max(rows, 2 + 2 * mm) if rows > 1 else 1
            nb = self._nb
            ws = {"m": mm, "rows": rr, "im": np.empty((mm, nb)), "den": np.empty((mm, nb)),
                  "Ju": np.empty((mm, nb), dtype=complex), "buf": np.zeros((rr, self._nspec), dtype=complex),
                  "w": np.empty((rr, self.model.n_fft))}
            for name in ("phi", "Y", "mu", "g", "th", "zc", "v"):
                ws[name] = np.empty(nb, dtype=complex)
            # real work buffers of velab.complexops (numpy's complex tanh, sqrt and division are
            # scalar loops: most of an evaluation)
            ws["r"] = np.empty((complexops.WORK, nb))
            ws["mask"] = np.empty(nb, dtype=bool)
            self._work = ws
        view = dict(ws)
        for name in ("im", "den", "Ju"):
            view[name] = ws[name][:m]
        view["buf"], view["w"] = ws["buf"][:rows], ws["w"][:rows]
        return view

    def _eval(self, a: float, J_rel: np.ndarray, tau: np.ndarray, jac: bool, tau_free: bool,
              out: np.ndarray | None = None) -> np.ndarray:
        """Rows: h, then (if jac) dh/d ln a, dh/d ln J'_k, [dh/d ln tau_k]."""
        m = J_rel.size
        rows = 1 + (1 + m + (m if tau_free else 0) if jac else 0)
        ws = self._buffers(m, rows)
        nb = self._nb
        self.evaluations += 1
        if jac:
            self.jacobians += 1
        if self.workers < 2 or nb < SPLIT_MIN_BINS:
            self._columns(ws, slice(0, nb), a, J_rel, tau, jac, tau_free)
            return self.model.sums_to_time(ws["buf"], out=out, work=ws["w"])
        # two halves: the bins, then the rows of the inverse FFT (each operation is per bin or per row)
        half = nb // 2
        both(lambda: self._columns(ws, slice(0, half), a, J_rel, tau, jac, tau_free),
             lambda: self._columns(ws, slice(half, nb), a, J_rel, tau, jac, tau_free))
        if out is None:
            out = np.empty((rows, self.n_t))
        if rows == 1:
            return self.model.sums_to_time(ws["buf"], out=out, work=ws["w"])
        r = (rows + 1) // 2
        buf, w = ws["buf"], ws["w"]
        both(lambda: self.model.sums_to_time(buf[:r], out=out[:r], work=w[:r]),
             lambda: self.model.sums_to_time(buf[r:], out=out[r:], work=w[r:]))
        return out

    def _columns(self, ws: dict, sl: slice, a: float, J_rel: np.ndarray, tau: np.ndarray, jac: bool,
                 tau_free: bool) -> None:
        """Fill the half-spectrum rows of ``ws["buf"]`` on the bins ``sl``: Z times the summed flow
        spectrum, then (if jac) the Jacobian columns. Touches only those bins of the work buffers."""
        m = J_rel.size
        if sl.start or sl.stop != self._nb:  # (a half of a split evaluation: views of its bins)
            ws = {k: (v[..., sl] if isinstance(v, np.ndarray) else v) for k, v in ws.items()}
            omega, sgA, W, mq, q2 = self._omega[sl], self._sgA[sl], self.W[sl], self._mq[sl], self._q2[sl]
        else:  # every bin: the per-bin buffers as they are, the spectrum's rows up to the band's last bin
            ws = dict(ws, buf=ws["buf"][..., :sl.stop])
            omega, sgA, W, mq, q2 = self._omega, self._sgA, self.W, self._mq, self._q2
        r = list(ws["r"])
        Y = ws["Y"]
        c0 = 1.0 / a**2
        if m:
            # J'_k u_k = J'_k / (1 + s tau_k), s = sigma + i omega, in real arithmetic into kept buffers
            # (no complex temporaries); phi = sum_k J'_k u_k; Y = (s gA / a^2)(1 + phi)
            re = 1.0 + self._sigma * tau
            im, den, Ju = ws["im"], ws["den"], ws["Ju"]
            np.multiply(omega[None, :], tau[:, None], out=im)
            np.multiply(im, im, out=den)
            den += (re * re)[:, None]
            np.divide((re * J_rel)[:, None], den, out=Ju.real)
            im *= -J_rel[:, None]
            np.divide(im, den, out=Ju.imag)
            phi = ws["phi"]
            if m == 1:
                np.copyto(phi, Ju[0])
            else:
                np.sum(Ju, axis=0, out=phi)
            phi += 1.0
            np.multiply(phi, sgA, out=Y)
            Y *= c0
        else:
            np.multiply(sgA, c0, out=Y)
        mu, g, th, zc = ws["mu"], ws["g"], ws["th"], ws["zc"]
        np.multiply(Y, W, out=mu)
        if complexops.ENABLED:
            complexops.sqrt(mu, mu, r, ws["mask"])
            np.multiply(mu, self.L, out=g)
            complexops.tanh(g, th, r)
            complexops.divide(mu, Y, zc, r)  # Zc
        else:
            np.sqrt(mu, out=mu)
            np.multiply(mu, self.L, out=g)
            np.tanh(g, out=th)
            np.divide(mu, Y, out=zc)
        b = ws["buf"]
        if self.position_m is not None:
            self._section_columns(ws, b, sl, jac, m, J_rel, tau_free, mq, q2)
            return
        np.multiply(zc, th, out=b[0])
        b[0] *= mq  # Z = -Zc tanh(mu L), times the summed flow spectrum
        if jac:
            # P = dZ/dY Y q = (Zc / 2)(tanh g - g sech^2 g) q
            v = ws["v"]
            np.multiply(th, th, out=v)
            np.subtract(1.0, v, out=v)
            v *= g
            np.subtract(th, v, out=v)
            P = zc
            P *= v
            P *= q2
            np.multiply(P, -2.0, out=b[1])  # dY/d ln a = -2 Y
            if m:
                # dY/d ln J'_k = Y J'_k u_k / (1 + phi);  dY/d ln tau_k = -(dY/d ln J'_k) s tau_k u_k,
                # and s tau_k u_k = 1 - u_k
                if complexops.ENABLED:
                    complexops.divide(P, phi, P, r)
                else:
                    P /= phi
                cJ = b[2 : 2 + m]
                np.multiply(Ju, P, out=cJ)
                if tau_free:
                    # Ju / J'_k - 1 (a complex divided by a real, part by part: what numpy's complex
                    # division gives, without its scalar loop)
                    ct = b[2 + m :]
                    np.divide(Ju.real, J_rel[:, None], out=ct.real)
                    np.divide(Ju.imag, J_rel[:, None], out=ct.imag)
                    ct -= 1.0
                    ct *= cJ

    def _section_columns(self, ws, b, sl, jac, m, J_rel, tau_free, mq, q2) -> None:
        """:meth:`_columns` at a section x: Z_x = -Zc r, r = sinh(mu x) / cosh(mu L) (velab.model), and
        dZ_x/dY = (Zc / 2Y)(r - mu x c + mu L r tanh(mu L)), c = cosh(mu x) / cosh(mu L) (x = L: the
        valve's (Zc / 2Y)(tanh g - g sech^2 g)). Plain arrays: the fits that use it are not the hot path."""
        x, L = self.position_m, self.L
        mu, th, zc = ws["mu"], ws["th"], ws["zc"]
        e = np.exp(-2.0 * mu * L)
        up, down = np.exp(mu * (x - L)), np.exp(-mu * (x + L))
        r = (up - down) / (1.0 + e)
        b[0] = zc * r * mq
        if not jac:
            return
        c = (up + down) / (1.0 + e)
        P = zc * (r - mu * x * c + mu * L * r * th) * q2  # dZ_x/dY Y q
        b[1] = -2.0 * P  # dY/d ln a = -2 Y
        if m:
            P = P / ws["phi"]
            Ju = ws["Ju"]
            cJ = b[2 : 2 + m]
            np.multiply(Ju, P, out=cJ)
            if tau_free:
                ct = b[2 + m :]
                np.divide(Ju, J_rel[:, None], out=ct)
                ct -= 1.0
                ct *= cJ

    def head(self, a: float, J_rel, tau, out: np.ndarray | None = None) -> np.ndarray:
        """h(t) for wave speed a (m/s) and KV elements J'_k (dimensionless), tau_k (s)."""
        o = None if out is None else out.reshape(1, -1)
        return self._eval(a, np.asarray(J_rel, dtype=float), np.asarray(tau, dtype=float), False, False, o)[0]

    def head_jac_x(self, a: float, J_rel, tau, tau_free: bool = True, out: np.ndarray | None = None):
        """h(t) and the Jacobian rows in the optimiser's variables, shape (k, n_t), C-ordered:
        d/d ln a, d/d ln J'_k, and d/d ln tau_k if ``tau_free``. ``out`` (1 + k, n_t) is
        filled if given."""
        res = self._eval(a, np.asarray(J_rel, dtype=float), np.asarray(tau, dtype=float), True, tau_free, out)
        return res[0], res[1:]


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
