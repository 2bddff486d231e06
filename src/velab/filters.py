"""The fit path's two low-pass filters, without scipy.signal (whose import, ~1.5 s, pulls in scipy.stats).

* the orifice coupling's zero-phase Butterworth (velab.fitting.flows): :func:`butter_lowpass_sos`,
  :func:`sosfilt`, :func:`sosfilt_zi`, :func:`sosfiltfilt`;
* the record's anti-alias decimation (velab.fitting.prepare): :func:`firwin_lowpass`, :func:`fir_decimate`.

Each is the documented math of its scipy.signal namesake (1.17: ``butter(..., output="sos")``, ``sosfilt``,
``sosfilt_zi``, ``sosfiltfilt`` with its default padding, ``firwin`` with the Hamming window,
``resample_poly(x, 1, q, window=h, padtype="line")``) carried out in the same order of floating-point
operations, so that the results are scipy's to the last bit on the platforms tried (tests/test_filters.py asks
1e-12): a fit's numbers must not depend on which of the two filtered its record (a changed last bit of the
coupling head once moved a fit to another closure, docs/performance.md, thirteenth round).

The two recursions (the biquad cascade, the decimating FIR's sums) are numba kernels, cached on disk like the
MOC's (velab.moc.kernel) and compiled without ``fastmath``: that would reorder the sums.
"""

from __future__ import annotations

import numpy as np
from numba import njit, uint64

# the Hamming window's coefficient: w = A0 - (1 - A0) cos(2 pi n / (M - 1)), as a generalized cosine window
HAMMING_A0 = 0.54


def butter_lowpass_sos(order: int, cutoff_hz: float, fs_hz: float) -> np.ndarray:
    """Second-order sections (n_sections, 6) of the digital Butterworth low-pass of ``order`` with its -3 dB
    point at ``cutoff_hz`` for the sample rate ``fs_hz`` (0 < cutoff < fs/2): scipy.signal's
    ``butter(order, cutoff_hz, fs=fs_hz, output="sos")``.

    The analogue prototype's poles -exp(i pi m / 2N), m = -N+1, -N+3, ..., N-1, scaled to the pre-warped cutoff
    4 tan(pi Wn / 2) (Wn the cutoff over Nyquist, the bilinear transform at fs = 2), mapped by z = (4 + s)/(4 - s);
    all N zeros at z = -1, and the gain that makes the product real. Sections by zpk2sos's "nearest" pairing: an
    odd order gets a pole and a zero at the origin; poles are taken closest to the unit circle first, each with
    the nearest remaining zeros, and the first taken is the last section; the gain goes to the first."""
    order = int(order)
    wn = 2.0 * float(cutoff_hz) / float(fs_hz)
    if order < 1 or not 0.0 < wn < 1.0:
        raise ValueError(f"a Butterworth low-pass needs order >= 1 and 0 < cutoff < fs/2 (got order {order}, "
                         f"cutoff {cutoff_hz!r} Hz at {fs_hz!r} Hz)")
    warped = 4.0 * np.tan(np.pi * wn / 2.0)  # numpy's tan and power, as scipy's: the last bits are the same
    p = -np.exp(1j * np.pi * np.arange(-order + 1, order, 2) / (2 * order)) * warped
    k = warped ** order
    pz = (4.0 + p) / (4.0 - p)
    kz = k * np.real(1.0 / np.prod(4.0 - p))
    # one pole of each conjugate pair; the odd order's real pole (-exp(0) is exactly real)
    poles = [(abs(abs(z) - 1.0), z) for z in pz if z.imag > 0] + [(abs(abs(z) - 1.0), z.real) for z in pz if z.imag == 0]
    zeros = [-1.0] * order + ([0.0] if order % 2 else [])
    sections = []
    for _, z in sorted(poles, key=lambda c: c[0]):  # stable: a tie keeps the prototype's order
        nearest = min(zeros, key=lambda w: abs(z - w))  # the first in the list on a tie: -1 before the origin
        zeros.remove(nearest)
        if isinstance(z, complex):
            # the conjugate pole and the next nearest zero; poly([z, conj z]) = [1, -2 Re z, |z|^2]
            other = min(zeros, key=lambda w: abs(z - w))
            a = [1.0, -2.0 * z.real, z.real * z.real + z.imag * z.imag]
        else:
            # the origin's pole, and the zero nearest to it
            other = min(zeros, key=abs)
            a = [1.0, -z, 0.0]
        zeros.remove(other)
        sections.append([1.0, -(nearest + other), nearest * other] + a)
    sos = np.array(sections[::-1])
    sos[0, :3] *= kz
    return sos


def sosfilt_zi(sos) -> np.ndarray:
    """The state (n_sections, 2) of the cascade's steady response to a unit step: scipy.signal's ``sosfilt_zi``.

    Per section the transposed direct form II's fixed point z = A z + B, A = companion(a)^T,
    B = b[1:] - a[1:] b0, i.e. (I - A) z = B, times the DC gain of the sections before it."""
    sos = _check_sos(sos)
    zi = np.empty((sos.shape[0], 2))
    scale = 1.0
    for s in range(sos.shape[0]):
        b, a = sos[s, :3], sos[s, 3:]
        i_minus_a = np.array([[1.0 + a[1], -1.0], [a[2], 1.0]])
        zi[s] = scale * np.linalg.solve(i_minus_a, b[1:] - a[1:] * b[0])
        scale *= b.sum() / a.sum()
    return zi


def sosfilt(sos, x, axis: int = -1, zi=None):
    """The cascade of second-order sections ``sos`` (a0 = 1) applied to ``x`` along ``axis`` (transposed direct
    form II): scipy.signal's ``sosfilt``. ``zi`` (n_sections, ..., 2, ...: x's shape with 2 on ``axis``) the
    initial state; then (y, final state) is returned, else y."""
    sos = _check_sos(sos)
    rows, shape, moved = _rows(x, axis)
    ns, ax = sos.shape[0], axis % len(shape)
    if zi is None:
        state = np.zeros((rows.shape[0], ns, 2))
    else:
        zi = np.asarray(zi, dtype=float)
        if zi.shape != (ns,) + _with(shape, ax, 2):
            raise ValueError(f"zi must have shape {(ns,) + _with(shape, ax, 2)} (got {zi.shape})")
        # (n_sections, ..., 2, ...) -> the kernel's (rows, n_sections, 2)
        state = np.array(np.moveaxis(zi, ax + 1, -1).reshape(ns, -1, 2).transpose(1, 0, 2), order="C")  # a copy
    _sos_rows(sos, rows, state, False)
    y = _unrows(rows, moved, axis)
    if zi is None:
        return y
    return y, np.moveaxis(state.transpose(1, 0, 2).reshape([ns] + moved[:-1] + [2]), -1, ax + 1)


def sosfiltfilt(sos, x, axis: int = -1) -> np.ndarray:
    """``sos`` applied forward and backward along ``axis`` (zero phase, the magnitude squared): scipy.signal's
    ``sosfiltfilt`` with its default padding.

    x is extended at each end by its odd reflection about the end sample, over 3 x (2 n_sections + 1 - the
    smaller of the counts of sections with b2 = 0 and with a2 = 0) samples (x must be longer than that); each
    pass starts from ``sosfilt_zi`` scaled by its first sample (the extension's, then the forward output's last)."""
    sos = _check_sos(sos)
    x = np.asarray(x, dtype=float)
    ntaps = 2 * sos.shape[0] + 1 - min(int((sos[:, 2] == 0).sum()), int((sos[:, 5] == 0).sum()))
    edge = 3 * ntaps
    n = x.shape[axis]
    if n <= edge:
        raise ValueError(f"the length of the input must be greater than the padding, which is {edge}")
    moved = np.moveaxis(x, axis, -1)
    rows = moved.reshape(-1, n)
    ext = np.concatenate([2.0 * rows[:, :1] - rows[:, edge:0:-1], rows,
                          2.0 * rows[:, -1:] - rows[:, -2:-(edge + 2):-1]], axis=1)
    zi = sosfilt_zi(sos)
    _sos_rows(sos, ext, zi[None, :, :] * ext[:, :1, None], False)
    _sos_rows(sos, ext, zi[None, :, :] * ext[:, -1:, None], True)  # backward, in place: no reversed copies
    return _unrows(ext[:, edge:-edge].copy(), list(moved.shape), axis)


def firwin_lowpass(numtaps: int, cutoff: float) -> np.ndarray:
    """The window-method FIR low-pass of ``numtaps`` taps, ``cutoff`` relative to Nyquist (0 < cutoff < 1), with the
    symmetric Hamming window and unit gain at DC: scipy.signal's ``firwin(numtaps, cutoff, window="hamming")``.

    h[n] = cutoff sinc(cutoff (n - (numtaps - 1)/2)) w[n] / sum of the same."""
    numtaps = int(numtaps)
    if numtaps < 1 or not 0.0 < cutoff < 1.0:
        raise ValueError(f"a FIR low-pass needs numtaps >= 1 and 0 < cutoff < 1 (got {numtaps}, {cutoff!r})")
    m = np.arange(0, numtaps) - 0.5 * (numtaps - 1)
    h = cutoff * np.sinc(cutoff * m)
    # the Hamming window as a generalized cosine window over [-pi, pi] (its coefficients 0.54 and 1 - 0.54)
    fac = np.linspace(-np.pi, np.pi, numtaps)
    w = np.zeros(numtaps)
    for j, c in enumerate((HAMMING_A0, 1.0 - HAMMING_A0)):
        w += c * np.cos(j * fac)
    h = h * w
    return h / np.sum(h)


def fir_decimate(x, h, q: int, axis: int = -1) -> np.ndarray:
    """Every q-th sample of x filtered by the FIR ``h`` centred on it: sample i of the result is
    sum_m h[m] x[i q + (len(h) - 1) // 2 - m], ceil(n / q) samples, x continued beyond its ends on the straight
    line through its first and last samples: scipy.signal's ``resample_poly(x, 1, q, window=h, padtype="line")``.
    A single sample has no line: NaN, as there."""
    q = int(q)
    h = np.asarray(h, dtype=float)
    if q < 1 or h.ndim != 1 or h.size < 1:
        raise ValueError("fir_decimate needs q >= 1 and a 1-D filter")
    x = np.asarray(x, dtype=float)
    if x.ndim == 0:
        raise ValueError("x must be at least 1-D")
    moved = list(np.moveaxis(x, axis, -1).shape)
    rows = np.moveaxis(x, axis, -1).reshape(-1, moved[-1])  # a view where it can be: ext below is a new array
    n = rows.shape[1]
    if n == 0:
        raise ValueError("fir_decimate needs at least one sample")
    if q == 1:
        return _unrows(rows.copy(), moved, axis)
    if n == 1:
        return _unrows(np.full((rows.shape[0], 1), np.nan), moved, axis)
    half = (h.size - 1) // 2
    left = h.size - 1 - half  # samples before the start the first output reaches (half, or half + 1 if even)
    n_out = -(-n // q)
    right = max(0, (n_out - 1) * q + half - (n - 1))  # and past the end the last one reaches
    slope = (rows[:, -1:] - rows[:, :1]) / (n - 1)
    ext = np.concatenate([rows[:, :1] + np.arange(-left, 0) * slope, rows,
                          rows[:, -1:] + np.arange(1, right + 1) * slope], axis=1)
    out = np.empty((rows.shape[0], n_out))
    # output i is sum_m h[m] ext[i q + half + left - m] with half + left = len(h) - 1, m from len(h) - 1 down to 0
    # (scipy's order of the sum): sum_k hr[k] ext[i q + k] with hr = h reversed, k upwards
    _fir_rows(ext, np.ascontiguousarray(h[::-1]), q, out)
    return _unrows(out, moved[:-1] + [n_out], axis)


def warm_up() -> None:
    """Load both kernels now (from numba's cache; compiled, ~1-2 s each, the first time on a machine): the
    GUI does it before its window shows, not on a worker thread that would hold the GIL meanwhile."""
    sosfiltfilt(butter_lowpass_sos(2, 0.1, 1.0), np.zeros(32))
    fir_decimate(np.zeros(8), np.full(3, 1.0 / 3.0), 2)


def _check_sos(sos) -> np.ndarray:
    sos = np.array(sos, dtype=float, order="C")  # a writable copy: a read-only array is another specialisation
    if sos.ndim != 2 or sos.shape[1] != 6 or sos.shape[0] < 1 or not np.all(sos[:, 3] == 1.0):
        raise ValueError("sos must have shape (n_sections, 6) with a0 = 1 in every section")
    return sos


def _rows(x, axis: int):
    """x as contiguous float64 rows (m, n) along ``axis`` (a copy: the kernels work in place), x's shape and its
    shape with ``axis`` moved last."""
    x = np.asarray(x, dtype=float)
    if x.ndim == 0:
        raise ValueError("x must be at least 1-D")
    moved = np.moveaxis(x, axis, -1)
    return np.array(moved.reshape(-1, moved.shape[-1]), order="C"), x.shape, list(moved.shape)


def _unrows(rows: np.ndarray, moved, axis: int) -> np.ndarray:
    return np.moveaxis(rows.reshape(moved), -1, axis)


def _with(shape, axis, value):
    s = list(shape)
    s[axis] = value
    return tuple(s)


@njit(cache=True, nogil=True)
def _sos_rows(sos, x, zi, backward):
    """Each row of x (m, n) through the cascade in place, from its last sample to its first if ``backward``;
    zi (m, n_sections, 2) the state, updated. Per sample and section: y = b0 v + z0, z0 = b1 v - a1 y + z1,
    z1 = b2 v - a2 y (v the section's input)."""
    m, n = x.shape
    ns = sos.shape[0]
    z = np.empty((ns, 2))  # the row's state apart from zi: the compiler need not reload it after each store to x
    for i in range(m):
        for s in range(ns):
            z[s, 0] = zi[i, s, 0]
            z[s, 1] = zi[i, s, 1]
        for k in range(n):
            j = n - 1 - k if backward else k
            v = x[i, j]
            for s in range(ns):
                y = sos[s, 0] * v + z[s, 0]
                z[s, 0] = sos[s, 1] * v - sos[s, 4] * y + z[s, 1]
                z[s, 1] = sos[s, 2] * v - sos[s, 5] * y
                v = y
            x[i, j] = v
        for s in range(ns):
            zi[i, s, 0] = z[s, 0]
            zi[i, s, 1] = z[s, 1]


@njit(cache=True, nogil=True)
def _fir_rows(ext, hr, q, out):
    """out[r, i] = sum over k = 0 .. L-1 of hr[k] ext[r, i q + k], each sum in that order (hr: the filter
    reversed, so that both run forward); four outputs at a time: four independent sums keep the CPU's adders
    busy, the order within each unchanged. The indices are unsigned: numba checks a signed one for
    wrap-around (a negative index counts from the end) at every access, which halved the speed."""
    rows, n_out = out.shape
    taps = uint64(hr.size)
    qu = uint64(q)
    for r in range(rows):
        e = ext[r]
        o = out[r]
        i = 0
        while i + 4 <= n_out:
            b = uint64(i * q)
            a0 = 0.0
            a1 = 0.0
            a2 = 0.0
            a3 = 0.0
            for k in range(taps):
                c = hr[k]
                a0 += c * e[b + k]
                a1 += c * e[b + qu + k]
                a2 += c * e[b + uint64(2) * qu + k]
                a3 += c * e[b + uint64(3) * qu + k]
            o[i] = a0
            o[i + 1] = a1
            o[i + 2] = a2
            o[i + 3] = a3
            i += 4
        while i < n_out:
            b = uint64(i * q)
            acc = 0.0
            for k in range(taps):
                acc += hr[k] * e[b + k]
            o[i] = acc
            i += 1
