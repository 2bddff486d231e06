"""Elementwise complex tanh, sqrt and division from real ufuncs, for the head model's hot loop.

numpy's complex ufuncs are scalar C loops (glibc's ctanh, csqrt; a division per element): on the
full band of a 20 s, 1 kHz window (20 251 bins) ``np.tanh`` takes about 5 ms, ``np.sqrt`` 1.2 ms and
``np.divide`` 0.65 ms, most of an evaluation (velab.fitting.engine). The same functions written with
numpy's vectorised ufuncs (tan, sinh, sqrt, |z|) cost a tenth of that and agree with numpy's
to a few units in the last place (tests/fitting/test_complexops.py), which moves a fitted parameter
by far less than its standard error.

Each function writes into ``out`` (complex; it may be an input itself) and takes real work buffers
``w`` (at least ``WORK`` float arrays of the input's length), so that an evaluation allocates nothing.
"""

from __future__ import annotations

import numpy as np

WORK = 5  # real work buffers each function needs
# the head model's evaluations (velab.fitting.engine, velab.model) use these functions; False: numpy's
# complex ufuncs (the baseline of benchmarks/fit_speed.py)
ENABLED = True

# tanh(x + iy) = 1 + i 4 sin y cos y exp(-2x) to double precision above this x: sinh is evaluated at
# most here so that its square stays finite (the imaginary part, below 1e-18, is then x = 22's)
_TANH_X_MAX = 22.0


def tanh(z: np.ndarray, out: np.ndarray, w: list) -> np.ndarray:
    """tanh(z) for Re z >= -22 (the model's g = mu L has Re g >= 0), Kahan's formula (as FreeBSD's
    ctanh): t = tan y, beta = 1 + t^2, s = sinh x, rho = sqrt(1 + s^2),
    tanh z = (beta rho s + i t) / (1 + beta s s)."""
    x, t, s, rho, den = w[:WORK]
    np.minimum(z.real, _TANH_X_MAX, out=x)
    np.tan(z.imag, out=t)
    np.sinh(x, out=s)
    np.multiply(t, t, out=x)
    x += 1.0  # beta
    np.multiply(s, s, out=rho)
    rho += 1.0
    np.sqrt(rho, out=rho)
    np.multiply(x, s, out=den)  # beta s
    rho *= den  # beta s rho (= (beta s) rho)
    den *= s
    den += 1.0  # 1 + beta s s
    np.divide(rho, den, out=out.real)
    np.divide(t, den, out=out.imag)
    return out


def sqrt(z: np.ndarray, out: np.ndarray, w: list, mask: np.ndarray) -> np.ndarray:
    """The principal square root (Re >= 0): t = sqrt((|z| + |x|) / 2), u = y / (2t); x >= 0: t + i u,
    else |u| + i copysign(t, y). ``mask`` a bool buffer of the input's length. z = 0 gives NaN (the
    model never evaluates s = 0: its bins sit at s = sigma + i omega, sigma > 0)."""
    a, ax, u, ua, tc = w[:WORK]
    x, y = z.real, z.imag
    np.greater_equal(x, 0.0, out=mask)
    np.abs(z, out=a)  # (numpy's |z| is vectorised, its hypot is not)
    np.abs(x, out=ax)
    a += ax
    a *= 0.5
    np.sqrt(a, out=a)  # t
    np.divide(y, a, out=u)
    u *= 0.5
    np.abs(u, out=ua)
    np.copysign(a, y, out=tc)
    # (z is read in full above: out may be z)
    np.copyto(out.real, ua)
    np.copyto(out.real, a, where=mask)
    np.copyto(out.imag, tc)
    np.copyto(out.imag, u, where=mask)
    return out


def divide(p: np.ndarray, q: np.ndarray, out: np.ndarray, w: list) -> np.ndarray:
    """p / q as p conj(q) / |q|^2, for q whose parts' squares neither overflow nor underflow (|q|
    between about 1e-150 and 1e150: the model's admittance and 1 + phi are within 1e-10..1e10)."""
    d, re, im = w[0], w[1], w[2]
    qr, qi, pr, pi = q.real, q.imag, p.real, p.imag
    np.multiply(qr, qr, out=d)
    np.multiply(qi, qi, out=re)
    d += re
    np.multiply(pr, qr, out=re)
    np.multiply(pi, qi, out=im)
    re += im
    np.multiply(pi, qr, out=im)
    np.multiply(pr, qi, out=w[3])
    im -= w[3]
    np.divide(re, d, out=out.real)
    np.divide(im, d, out=out.imag)
    return out
