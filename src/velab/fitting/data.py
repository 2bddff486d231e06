"""The calibration window of a record, checked, and its low-passed decimated copy."""

from __future__ import annotations

import math

import numpy as np

from velab.errors import DataError
from velab.fitting.window import MIN_WINDOW_SAMPLES, enough_samples, window_slice


def prepare_window(t_s, h_m, window_s: float | None):
    """Check and cut the record to the calibration window: samples with 0 <= t < window_s.

    Returns (t, h) starting at the trigger. Raises DataError (one line) for a bad record.
    """
    t = np.asarray(t_s, dtype=float)
    h = np.asarray(h_m, dtype=float)
    if t.ndim != 1 or h.shape != t.shape:
        raise DataError(f"time and head must be 1-D arrays of equal length (got {t.shape} and {h.shape})")
    if not enough_samples(t.size):
        raise DataError(f"record too short to calibrate ({t.size} samples)")
    dt = np.diff(t)
    step = float(np.median(dt))
    if not step > 0 or np.max(np.abs(dt - step)) > 1e-3 * step:
        raise DataError("time axis is not uniformly sampled")
    i0 = window_slice(t, 0.0, 0.0, 1.0 / step).start
    if i0 >= t.size:
        raise DataError("record has no samples after the trigger")
    if window_s is None:
        i1 = t.size
    else:
        if not window_s > 0:
            raise DataError(f"window must be positive, got {window_s:g} s")
        available = t[-1] - t[i0] + step
        if window_s > available * (1 + 1e-9) + 1e-9:
            raise DataError(f"window {window_s:g} s is longer than the record ({available:.6g} s after the trigger)")
        i1 = window_slice(t, 0.0, window_s, 1.0 / step).stop
    tw, hw = t[i0:i1], h[i0:i1]
    if tw.size < MIN_WINDOW_SAMPLES:
        raise DataError(f"window too short to calibrate ({tw.size} samples after the trigger)")
    bad = ~np.isfinite(hw)
    if bad.any():
        j = int(np.argmax(bad))
        raise DataError(f"head contains {int(bad.sum())} NaN/inf values in the window (first at t = {tw[j]:.6g} s)")
    if not np.all(np.isfinite(tw)):
        raise DataError("time axis contains NaN/inf values")
    return tw, hw


def lowpass_decimate(h: np.ndarray, q: int) -> np.ndarray:
    """Ideal low-pass at the Nyquist frequency of every q-th sample (even extension), decimated.

    The record mirrored at its end (h, h reversed: the half-sample symmetric extension of a type-II DCT, so the
    ends do not ring) is transformed, every bin from ceil(n / q) on is zeroed (the DCT coefficients from there on)
    and the first n samples of the inverse are kept. numpy.fft, not scipy.fft: scipy.fft's import (~0.9 s) was the
    largest part of a ``velab fit`` process's start-up, and a type-II DCT truncated this way is the same low-pass
    (to rounding: 3e-15)."""
    if q <= 1:
        return h.copy()
    h = np.asarray(h, dtype=float)
    n = h.size
    spec = np.fft.rfft(np.concatenate([h, h[::-1]]))
    spec[int(math.ceil(n / q)):] = 0.0
    return np.fft.irfft(spec, 2 * n)[:n:q]
