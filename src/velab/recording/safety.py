"""Safety: the surge interlock (and its downsurge against cavitation), the pressure ceiling, the output-directory check.

Pure functions (no I/O but the directory probe), each tested alone. Per-sample quality is the
drivers' (``SampleBlock.sample_quality``: NE43 limits, open loop, NaN, stuck counts, device
fault bits): the one source, used as it comes. What stays here is what a driver cannot judge,
because it needs the rig: the pressure ceiling (the pipe's rating and the transducer's span
as head) and the surge interlock. A sensor fault is a sensor fault: a 22 mA loop current is
``sensor_fault``, not a measurement, and never trips the ceiling; an over-range sample (a
measurement: the pressure is at least this) does.
"""

from __future__ import annotations

import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from velab.cavitation import predict_downsurge
from velab.rig import Rig
from velab.drivers.base import GRAVITY_M_S2, Quality
from velab.drivers.blocks import MEASUREMENT_CODES, QUALITY_CODE, QUALITY_CODES
from velab.errors import VelabError
from velab.recording.settings import RecordSettings
from velab.recording.types import RunRefused

OK = QUALITY_CODE[Quality.OK]


@dataclass(frozen=True)
class SurgePrediction:
    steady_head_m: float
    surge_m: float
    peak_head_m: float
    peak_pressure_pa: float
    limit_pa: float
    limiting: str  # "transducer full scale" | "pipe pressure rating"
    allowed: bool  # neither the peak over the limit nor the downsurge at the vapour-pressure head
    message: str
    # the first downsurge against column separation (velab.cavitation)
    min_head_m: float = math.nan
    vapour_head_m: float = math.nan
    cavitation: bool = False
    # the run's pressure ceiling (velab.recording.safety.ceiling_head): a peak at or above it is refused too,
    # since aborting after the closure cannot stop the surge
    ceiling_m: float = math.nan
    over_ceiling: bool = False


def predict_surge(rig: Rig, settings: RecordSettings, steady_head_m: float | None = None,
                  steady_flow_m3_s: float | None = None) -> SurgePrediction:
    """Joukowsky surge a*dQ/(g A) over the steady head, plus margin, against the rig's limits; and the
    same below the steady head against the vapour-pressure head (column separation, velab.cavitation),
    and the peak against the run's pressure ceiling (``ceiling_head``): each refused before anything moves.

    Conservative on both sides: the peak from the higher of the measured and the rig's steady head,
    the downsurge from the lower one, and from the measured flow if given, else from the highest flow
    the readiness check lets through (the rig's Q0 plus the flow tolerance)."""
    rho_g = rig.fluid.density_kg_m3 * GRAVITY_M_S2
    h0 = rig.steady_head_m if steady_head_m is None else max(float(steady_head_m), rig.steady_head_m)
    dq_frac = (100.0 - settings.end_position_pct) / 100.0
    low = rig.steady_head_m if steady_head_m is None else min(float(steady_head_m), rig.steady_head_m)
    flow = rig.steady_flow_m3_s * (1.0 + settings.flow_tolerance) if steady_flow_m3_s is None else steady_flow_m3_s
    down = predict_downsurge(rig, low, flow, surge_margin=settings.surge_margin, closed_fraction=dq_frac)
    surge = rig.joukowsky_head_m() * dq_frac * (1.0 + settings.surge_margin)
    peak = h0 + surge
    peak_pa = peak * rho_g
    limit_pa, limiting = limit_pressure(rig)
    allowed = peak_pa <= limit_pa
    verdict = "within" if allowed else "EXCEEDS"
    msg = (f"predicted peak {peak:.1f} m ({peak_pa / 1e5:.2f} bar) = steady {h0:.1f} m + Joukowsky surge "
           f"{surge:.1f} m (margin {settings.surge_margin:.0%}) {verdict} the {limiting} "
           f"({limit_pa / 1e5:.2f} bar = {limit_pa / rho_g:.1f} m)")
    ceiling = ceiling_head(rig, settings)
    over = allowed and peak >= ceiling
    if not allowed:
        msg = "manoeuvre refused: " + msg
        if not down.allowed:
            msg += "; and " + down.message.removeprefix("manoeuvre refused: ")
    elif over:
        where = "the run's setting" if settings.ceiling_head_m is not None else "95 % of the limiting pressure"
        msg = (f"manoeuvre refused: predicted peak {peak:.1f} m = steady {h0:.1f} m + Joukowsky surge {surge:.1f} m "
               f"(margin {settings.surge_margin:.0%}) reaches the pressure ceiling {ceiling:.1f} m ({where}): "
               "an abort after the closure cannot stop the surge; raise the ceiling, slow the closure (beta) "
               "or close partly (end position)")
        if not down.allowed:
            msg += "; and " + down.message.removeprefix("manoeuvre refused: ")
    elif not down.allowed:
        msg = down.message  # one line naming cavitation and the vapour-pressure head
    return SurgePrediction(h0, surge, peak, peak_pa, limit_pa, limiting, allowed and not over and down.allowed, msg,
                           down.min_head_m, down.vapour_head_m, not down.allowed, ceiling, over)


def check_manoeuvre(valve, name: str, beta_per_s: float, gamma: float, end_position_pct: float) -> None:
    """The manoeuvre against what the valve's actuator accepts, before anything is armed: VelabError (exit 2,
    bad input) naming the value and the limit. A driver that knows its own limits says so through its
    ``check_manoeuvre(beta, gamma, end)``; else the ranges of its device profile's beta, gamma and
    end_position registers (velab.drivers.profile); a valve without either takes any manoeuvre."""
    own = getattr(valve, "check_manoeuvre", None)
    try:
        if callable(own):
            own(beta_per_s, gamma, end_position_pct)
            return
        profile = getattr(valve, "profile", None)
        registers = getattr(profile, "registers", None)
        if not isinstance(registers, dict):
            return
        for reg, value in (("beta", beta_per_s), ("gamma", gamma), ("end_position", end_position_pct)):
            spec = registers.get(reg)
            if spec is not None and hasattr(spec, "check_range"):
                spec.check_range(float(value))
    except ValueError as exc:  # (the drivers' RangeError is a ValueError too)
        where = getattr(getattr(valve, "profile", None), "path", None)
        text = " ".join(str(exc).removeprefix(f"{name}: ").split())
        raise VelabError(f"manoeuvre outside the valve actuator's profile: {name}: {text}"
                         + (f" ({where})" if where else "") + "; nothing was armed") from None


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


def describe_codes(codes: np.ndarray) -> str:
    """'stale 120, over_range 3' for the non-OK codes of a block (the worst first)."""
    vals, counts = np.unique(codes[codes != OK], return_counts=True)
    order = np.argsort(-counts)
    return ", ".join(f"{QUALITY_CODES[int(vals[i])].value} {int(counts[i])}" for i in order)


def ceiling_crossing(head: np.ndarray, codes: np.ndarray, ceiling_m: float) -> int | None:
    """Index of the first measured sample (ok, over or under range) above the ceiling, or None;
    samples that are not measurements (sensor fault, open loop, NaN, stuck, device fault) never trip it."""
    with np.errstate(invalid="ignore"):
        over = (head > ceiling_m) & np.isin(codes, MEASUREMENT_CODES)
    idx = np.flatnonzero(over)
    return int(idx[0]) if idx.size else None


def finite_max(x: np.ndarray) -> float:
    with np.errstate(invalid="ignore"):
        return float(np.nanmax(x)) if np.isfinite(x).any() else -math.inf
