"""The calibration window of a record, checked, and its low-passed decimated copy."""

from __future__ import annotations

import math

import numpy as np
import scipy.fft as sfft

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
    """Ideal low-pass at the Nyquist frequency of every q-th sample (DCT, even extension), decimated."""
    if q <= 1:
        return h.copy()
    c = sfft.dct(h, type=2, norm="ortho")
    n = h.size
    keep = int(math.ceil(n / q))
    c[keep:] = 0.0
    return sfft.idct(c, type=2, norm="ortho")[::q]
