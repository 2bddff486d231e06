"""A record's domain rules, each stated once: the baseline before the trigger, the steady head, the
fit window's cut and its minimum size.

The fit path (velab.fitting.prepare), the recorder's time line (velab.recording.timeline), the run
file's reader (velab.runfiles.reader) and the fitter's window check (velab.fitting.data) all ask
this module, so that an online fit, an offline re-fit and the recorder's summary agree on the
same samples. numpy only: the recorder asks it without loading the fitter (scipy).

The steady head is the mean of the *baseline*: the finite samples before the trigger, after the
last non-finite one, at most ``BASELINE_S`` long. Why the whole baseline and not a short span
next to the trigger: the head is steady there (the valve has not moved), so the mean's error
falls as 1/sqrt(n_eff); a 0.3 mm error moved S3's dAIC by about 10 on low-noise records, which
decided S3 against S4. ``BASELINE_S`` bounds what the recorder keeps in memory, and makes the
offline fit of a run with a long armed wait see the same baseline as its online fit.
"""

from __future__ import annotations

import numpy as np

BASELINE_S = 3.0  # the baseline is at most this long (the recorder keeps this much before the trigger)
MIN_WINDOW_SAMPLES = 16  # fewer samples after the trigger cannot calibrate a model


def baseline_slice(t: np.ndarray, head: np.ndarray, trigger_time_s: float, rate_hz: float) -> slice:
    """The baseline's indices in ``t``: [trigger - BASELINE_S, trigger) with the window's half-sample
    rule, after the last non-finite head sample (a gap in the baseline breaks it)."""
    half = 0.5 / rate_hz
    i0, i1 = (int(i) for i in np.searchsorted(t, [trigger_time_s - BASELINE_S - half, trigger_time_s - half]))
    bad = np.flatnonzero(~np.isfinite(np.asarray(head[i0:i1], dtype=float)))
    if bad.size:
        i0 += int(bad[-1]) + 1
    return slice(i0, i1)


def steady_head(t: np.ndarray, head: np.ndarray, trigger_time_s: float, fallback: float,
                rate_hz: float | None = None) -> float:
    """Mean of the baseline's head; ``fallback`` (the rig's steady head) if there is no baseline.
    ``rate_hz``: the record's rate (default: from the axis)."""
    t = np.asarray(t, dtype=float)
    if rate_hz is None:
        rate_hz = 1.0 / float(np.median(np.diff(t))) if t.size > 1 else 1.0
    pre = np.asarray(head, dtype=float)[baseline_slice(t, head, trigger_time_s, rate_hz)]
    return float(pre.mean()) if pre.size else float(fallback)


def window_slice(t: np.ndarray, trigger_time_s: float, window_s: float, rate_hz: float) -> slice:
    """The fit window's indices in ``t``: trigger - dt/2 <= t < trigger + window - dt/2."""
    half = 0.5 / rate_hz
    i0, i1 = np.searchsorted(t, [trigger_time_s - half, trigger_time_s + window_s - half])
    return slice(int(i0), int(i1))


def enough_samples(n: int) -> bool:
    return n >= MIN_WINDOW_SAMPLES
