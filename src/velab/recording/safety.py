"""Safety: the surge interlock, the pressure ceiling, the output-directory check, sensor plausibility.

Pure functions and one small stateful checker (no I/O but the directory probe): each can be
tested alone. A sensor fault is a sensor fault: a 22 mA loop current is flagged OVER_RANGE
(and never counted as a pressure-ceiling crossing, which only OK samples can make).
"""

from __future__ import annotations

import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from velab.config import Rig
from velab.drivers.base import GRAVITY_M_S2, Quality
from velab.drivers.blocks import QUALITY_CODE, QUALITY_CODES
from velab.recording.settings import RecordSettings
from velab.recording.types import RunRefused

# NAMUR NE43: 3.8..20.5 mA is the measuring range of a 4-20 mA loop; beyond it the transmitter
# signals a failure (below 3.6 mA: open loop)
LOOP_MIN_MA, LOOP_MAX_MA, OPEN_LOOP_MA = 3.8, 20.5, 3.6
OK, STALE = QUALITY_CODE[Quality.OK], QUALITY_CODE[Quality.STALE]


@dataclass(frozen=True)
class SurgePrediction:
    steady_head_m: float
    surge_m: float
    peak_head_m: float
    peak_pressure_pa: float
    limit_pa: float
    limiting: str  # "transducer full scale" | "pipe pressure rating"
    allowed: bool
    message: str


def predict_surge(rig: Rig, settings: RecordSettings, steady_head_m: float | None = None) -> SurgePrediction:
    """Joukowsky surge a*dQ/(g A) over the steady head, plus margin, against the rig's limits."""
    rho_g = rig.fluid.density_kg_m3 * GRAVITY_M_S2
    h0 = rig.steady_head_m if steady_head_m is None else max(float(steady_head_m), rig.steady_head_m)
    dq_frac = (100.0 - settings.end_position_pct) / 100.0
    surge = rig.joukowsky_head_m() * dq_frac * (1.0 + settings.surge_margin)
    peak = h0 + surge
    peak_pa = peak * rho_g
    limit_pa, limiting = limit_pressure(rig)
    allowed = peak_pa <= limit_pa
    verdict = "within" if allowed else "EXCEEDS"
    msg = (f"predicted peak {peak:.1f} m ({peak_pa / 1e5:.2f} bar) = steady {h0:.1f} m + Joukowsky surge "
           f"{surge:.1f} m (margin {settings.surge_margin:.0%}) {verdict} the {limiting} "
           f"({limit_pa / 1e5:.2f} bar = {limit_pa / rho_g:.1f} m)")
    if not allowed:
        msg = "manoeuvre refused: " + msg
    return SurgePrediction(h0, surge, peak, peak_pa, limit_pa, limiting, allowed, msg)


def limit_pressure(rig: Rig) -> tuple[float, str]:
    """The lower of the transducer's full scale and the pipe's pressure rating (Pa), and which it is."""
    limits = [(rig.transducer.full_scale_pa, "transducer full scale")]
    if rig.pipe.pressure_rating_pa is not None:
        limits.append((rig.pipe.pressure_rating_pa, "pipe pressure rating"))
    return min(limits)


def max_ceiling_head(rig: Rig) -> float:
    """The highest ceiling an operator may set: the limiting pressure, as head."""
    return limit_pressure(rig)[0] / (rig.fluid.density_kg_m3 * GRAVITY_M_S2)


def ceiling_head(rig: Rig, settings: RecordSettings) -> float:
    """The pressure ceiling (m): the setting (never above the limiting pressure), else 95 % of it."""
    top = max_ceiling_head(rig)
    if settings.ceiling_head_m is not None:
        return min(float(settings.ceiling_head_m), top)
    return 0.95 * top


def check_output_dir(out_dir: Path, planned_bytes: int) -> None:
    """Refuse (RunRefused) a missing, unwritable or too-full output directory."""
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise RunRefused(f"{out_dir}: output directory does not exist")
    if not os.access(out_dir, os.W_OK | os.X_OK):
        raise RunRefused(f"{out_dir}: output directory is not writable")
    probe = out_dir / f".velab-write-test-{os.getpid()}"
    try:
        probe.write_bytes(b"x")
        probe.unlink()
    except OSError as exc:
        raise RunRefused(f"{out_dir}: output directory is not writable ({exc.strerror or exc})") from None
    free = shutil.disk_usage(out_dir).free
    need = 2 * planned_bytes + (16 << 20)
    if free < need:
        raise RunRefused(f"{out_dir}: too little free space for the planned run "
                         f"({free / 1e6:.1f} MB free, {need / 1e6:.1f} MB needed)")


class SensorCheck:
    """Per-sample plausibility of one analogue channel, block after block.

    Codes (uint8, ``velab.drivers.blocks.QUALITY_CODES``) start from the driver's per-sample
    quality when it gives one, and add: NaN (value or signal), loop current outside
    3.8..20.5 mA (below 3.6 mA: open loop), and a stuck channel (identical raw counts for more
    than ``stuck_samples`` samples in a row, across blocks: a live transducer's noise always
    moves the last bits). ``stuck_samples=None`` disables the stuck test (a valve-position
    feedback legitimately sits still at its ends).
    """

    def __init__(self, stuck_samples: int | None):
        self.stuck_samples = stuck_samples
        self._run_value = None
        self._run_len = 0

    def codes(self, raw: np.ndarray, signal: np.ndarray, values: np.ndarray, signal_units: str = "mA",
              driver_codes: np.ndarray | None = None) -> np.ndarray:
        n = raw.shape[0]
        q = np.zeros(n, np.uint8) if driver_codes is None else np.asarray(driver_codes, np.uint8).copy()
        if signal_units == "mA":
            with np.errstate(invalid="ignore"):
                q[(q == OK) & (signal > LOOP_MAX_MA)] = QUALITY_CODE[Quality.OVER_RANGE]
                q[(q == OK) & (signal < LOOP_MIN_MA)] = QUALITY_CODE[Quality.UNDER_RANGE]
                q[signal < OPEN_LOOP_MA] = QUALITY_CODE[Quality.OPEN_LOOP]
        q[~np.isfinite(values) | ~np.isfinite(signal)] = QUALITY_CODE[Quality.NAN]
        if self.stuck_samples:
            self._stuck(np.asarray(raw).astype(np.int64), q)
        return q

    def _stuck(self, raw: np.ndarray, q: np.ndarray) -> None:
        if raw.size == 0:
            return
        change = np.flatnonzero(np.diff(raw)) + 1
        starts = np.concatenate([[0], change])
        ends = np.concatenate([change, [raw.size]])
        for a, b in zip(starts, ends):
            carried = self._run_len if (a == 0 and raw[0] == self._run_value) else 0
            if carried + (b - a) > self.stuck_samples:
                first = max(a, a + self.stuck_samples - carried)
                seg = q[first:b]
                seg[seg == OK] = STALE
        last = starts[-1]
        self._run_len = raw.size - last + (self._run_len if last == 0 and raw[0] == self._run_value else 0)
        self._run_value = raw[-1]


def describe_codes(codes: np.ndarray) -> str:
    """'stale 120, over_range 3' for the non-OK codes of a block (the worst first)."""
    vals, counts = np.unique(codes[codes != OK], return_counts=True)
    order = np.argsort(-counts)
    return ", ".join(f"{QUALITY_CODES[int(vals[i])].value} {int(counts[i])}" for i in order)


def ceiling_crossing(head: np.ndarray, codes: np.ndarray, ceiling_m: float) -> int | None:
    """Index of the first OK sample above the ceiling (flagged samples never trip it), or None."""
    with np.errstate(invalid="ignore"):
        over = (head > ceiling_m) & (codes == OK)
    idx = np.flatnonzero(over)
    return int(idx[0]) if idx.size else None


def finite_max(x: np.ndarray) -> float:
    with np.errstate(invalid="ignore"):
        return float(np.nanmax(x)) if np.isfinite(x).any() else -math.inf
