"""The measured stroke: the paper's sigmoid fitted to the recorded valve position of a fired valve.

A fired actuator runs its own stroke; what the interlock and the fit need of it is the sigmoid the
paper describes the closure with, in position: p(t) = end + (100 - end) / (1 + exp(beta (t - t0) + gamma)),
t0 the run's trigger instant (the file's trigger_time: measured from the position where it could be). Between 10 and 90 % of the stroke, ln(100 / o - 1) (o the opening of
the stroke, velab.recording.timeline.stroke_opening_pct) is linear in t: beta its slope, gamma its
value at t0; a least-squares line on those samples, then the sigmoid's residual in position as the
check that the stroke was a sigmoid at all.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from velab.recording.timeline import STROKE_BAND_PCT, stroke_opening_pct

MIN_SAMPLES = 5  # a line through fewer points of the stroke tells nothing about its shape


@dataclass(frozen=True)
class Stroke:
    """A measured stroke: beta (1/s), gamma (at the fire instant), end (% open), the residual of the
    sigmoid in position (% open, RMS over the stroke's band) and how many samples it was fitted on."""

    beta_per_s: float
    gamma: float
    end_position_pct: float
    rms_pct: float
    samples: int

    @property
    def closure_s(self) -> float:
        """90 % -> 10 % of the stroke: ln(81) / beta."""
        return math.log(81.0) / self.beta_per_s

    def to_dict(self) -> dict:
        return asdict(self) | {"closure_s": self.closure_s}


def fit_stroke(t: np.ndarray, position_pct: np.ndarray, t0: float, end_pct: float | None = None) -> Stroke | None:
    """The sigmoid of the recorded position ``position_pct`` (% open) on the time axis ``t`` (s), gamma at
    ``t0`` (the trigger instant on that axis); ``end_pct`` the stroke's end (default: the median of the last
    tenth of the record after the stroke, clipped to 0..50 %). None when fewer than MIN_SAMPLES samples
    lie inside the stroke's 10..90 % band (no stroke, or sampled too slowly to tell its shape)."""
    t = np.asarray(t, dtype=float)
    p = np.asarray(position_pct, dtype=float)
    ok = np.isfinite(t) & np.isfinite(p)
    t, p = t[ok], p[ok]
    if t.size < MIN_SAMPLES:
        return None
    if end_pct is None:
        after = p[t > t0]
        tail = after[-max(1, after.size // 10):] if after.size else p[-1:]
        end_pct = float(np.clip(np.median(tail), 0.0, 50.0))
    o = stroke_opening_pct(p, end_pct)
    lo, hi = STROKE_BAND_PCT
    sel = (o > lo) & (o < hi) & (t >= t0)
    if sel.sum() < MIN_SAMPLES:
        return None
    y = np.log(100.0 / o[sel] - 1.0)
    slope, intercept = np.polyfit(t[sel] - t0, y, 1)
    if not (slope > 0 and math.isfinite(slope) and math.isfinite(intercept)):
        return None
    model = end_pct + (100.0 - end_pct) / (1.0 + np.exp(np.clip(slope * (t[sel] - t0) + intercept, -700, 700)))
    rms = float(np.sqrt(np.mean((model - p[sel]) ** 2)))
    return Stroke(float(slope), float(intercept), float(end_pct), rms, int(sel.sum()))
