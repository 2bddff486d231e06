"""Redundant measurements compared: the same quantity seen by two instruments must agree within
what the two instruments' accuracies allow; beyond that one of them is wrong, and the run says so.

Three comparisons, each a pure function (values and tolerances in, a ``Finding`` or None out):

* ``position_mismatch``: the actuator's reported position (its status poll, at the instant its
  own controller stamps: trigger + time since trigger) against the ADC's valve-position channel
  over the instants that reply can stand for. A payload byte flipped on a Modbus TCP link (no
  checksum) gives a plausible wrong position that no protocol check can see: only this catches it.
* ``flow_mismatch``: the flowmeter's steady flow before the trigger against the rig's Q0 (the
  readiness check refuses a flow off Q0 at arm; this covers the baseline after it).
* ``head_mismatch``: the transducer's steady head (pretrigger mean) against the rig's prediction.

``RedundancyMonitor`` collects what the run sees (ADC blocks, valve polls, flow polls) from the
acquisition and slow threads and runs the comparisons once, at the end of the run.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field

import numpy as np

from velab.drivers.base import pressure_to_head_m
from velab.valvelaw import commanded_position_pct

# The position feedback (potentiometer on the ADC) and the actuator's own encoder each within 1 %
# of stroke: two readings of one position may differ by 2 % of stroke.
POSITION_ACCURACY_PCT = 2.0
# The instant a status reply stands for, on the ADC's axis: the actuator stamps its position with
# its time since trigger (same register block, one controller cycle); the trigger is measured from
# the feedback to a sample or two. The ADC range over +-this much around that instant is allowed:
# during a fast closure the valve moves that far between the two instruments' sample instants.
POSITION_TIMING_S = 0.02
# A RUNNING reply is also compared with the commanded stroke at its own time since trigger
# (stroke_mismatch): a real actuator follows its profile within a controller's lag. Placed replies
# measured on the simulated bench, loaded host, fast clock: within 0.5 ms of where the ADC saw their
# position (the 0.3 s once seen was a reply whose state was read before a trigger and its position
# after: the valve driver now reads the state again then, velab.drivers.valve.read_status).
FOLLOWING_S = 0.05
# States before this run's trigger: the valve is still whatever the time since trigger says (an actuator
# may keep its last run's until the next trigger; the driver reads the state again when a trigger falls
# between its two block reads, so a still state is never older than the position beside it)
STILL = ("IDLE", "ARMED")
# Before the trigger the actuator stamps nothing (time since trigger 0): the valve is still, and
# the reply is compared with the ADC's whole baseline.
# Electromagnetic flowmeter (SITRANS F M MAG 6000): 0.2-0.4 % of rate; 0.5 % with installation.
FLOW_METER_ACCURACY = 0.005
# The reservoir's level as set on the rig against the rig file's reservoir head (a float valve or
# an overflow weir holds it within a few cm; 0.5 m allows for a tank being refilled).
RESERVOIR_MARGIN_M = 0.5

POSITION_MISMATCH, FLOW_MISMATCH, HEAD_MISMATCH = "position_mismatch", "flow_mismatch", "head_mismatch"


@dataclass(frozen=True)
class Finding:
    """A disagreement beyond the tolerance: ``kind`` names it, ``role`` the instrument to suspect
    first, ``deviation`` and ``tolerance`` in the quantity's units, ``at_s`` where on the run's axis."""

    kind: str
    role: str
    message: str
    deviation: float
    tolerance: float
    at_s: float | None = None
    extras: dict = field(default_factory=dict)


def adc_range(t: np.ndarray, pos: np.ndarray, t_lo: float, t_hi: float) -> tuple[float, float] | None:
    """(min, max) of the ADC position over [t_lo, t_hi] (``t`` increasing, NaN = no position), the ends
    linearly interpolated on the sample axis; None when no finite sample lies within two sample
    spacings of the span (a gap in the record is not bridged: no data, no verdict)."""
    t, pos = np.asarray(t, float), np.asarray(pos, float)
    if t.size < 2:
        return None
    dt = float(np.median(np.diff(t[-64:])))  # the end: full rate (the start may be a still baseline, reduced)
    i0, i1 = np.searchsorted(t, [t_lo - 2 * dt, t_hi + 2 * dt])
    tt, pp = t[i0:i1], pos[i0:i1]
    ok = np.isfinite(pp)
    tt, pp = tt[ok], pp[ok]
    if tt.size == 0:
        return None
    inside = pp[(tt >= t_lo) & (tt <= t_hi)]
    ends = np.interp([max(t_lo, tt[0]), min(t_hi, tt[-1])], tt, pp)
    vals = np.concatenate([inside, ends])
    return float(vals.min()), float(vals.max())


def position_mismatch(reported_pct: float, at_s: float, t: np.ndarray, pos: np.ndarray,
                      timing_s: float = POSITION_TIMING_S, accuracy_pct: float = POSITION_ACCURACY_PCT,
                      t_span: tuple[float, float] | None = None) -> Finding | None:
    """The actuator reported ``reported_pct`` at ``at_s`` (the run's axis); the ADC channel ``pos``
    sampled at ``t``. Allowed: the ADC's range over [at - timing, at + timing] (what the valve moved
    between the two sample instants, from the ADC channel itself) widened by the accuracy.
    ``t_span`` replaces that window (a still valve: the whole baseline)."""
    if not math.isfinite(reported_pct):
        return None  # a NaN reply is flagged by the driver's quality already
    span = t_span if t_span is not None else (at_s - timing_s, at_s + timing_s)
    r = adc_range(t, pos, *span)
    if r is None:
        return None
    lo, hi = r
    dev = max(lo - reported_pct, reported_pct - hi, 0.0)
    if dev <= accuracy_pct:
        return None
    ref = f"{lo:.1f} % open" if hi - lo < 0.05 else f"{lo:.1f}..{hi:.1f} % open"
    return Finding(POSITION_MISMATCH, "valve",
                   f"position mismatch: the actuator reported {reported_pct:.1f} % open at t = {at_s:.3f} s, "
                   f"the ADC's position channel read {ref} around it: {dev:.1f} % of stroke apart, beyond "
                   f"the {accuracy_pct:g} % the two instruments allow (a corrupted reply or a failing feedback)",
                   dev, accuracy_pct, at_s, {"reported_pct": reported_pct, "adc_lo_pct": lo, "adc_hi_pct": hi})


def stroke_mismatch(reported_pct: float, since_trigger_s: float, profile: tuple[float, float, float],
                    trigger_s: float | None) -> Finding | None:
    """A RUNNING reply against the commanded stroke at the reply's own time since trigger: the stroke the
    ADC's channel recorded (the recorder measures the trigger by fitting this profile to that channel).
    The actuator stamps its position with its own clock, so no host timing enters: a mid-stroke reply the
    host cannot place well enough for ``position_mismatch`` (docs/recording.md) is still checked. Allowed:
    the two instruments' accuracy plus what the stroke moves in FOLLOWING_S (a real actuator's following
    lag)."""
    if not (math.isfinite(reported_pct) and math.isfinite(since_trigger_s) and since_trigger_s > 0):
        return None
    beta, gamma, end = profile
    expected = float(commanded_position_pct(since_trigger_s, beta, gamma, end))
    slope = abs(expected - end) * (1.0 - (expected - end) / max(100.0 - end, 1e-9)) * beta  # dp/dt of the sigmoid
    tol = POSITION_ACCURACY_PCT + slope * FOLLOWING_S
    dev = abs(reported_pct - expected)
    if dev <= tol:
        return None
    at = trigger_s + since_trigger_s if trigger_s is not None else None
    return Finding(POSITION_MISMATCH, "valve",
                   f"position mismatch: the actuator reported {reported_pct:.1f} % open {since_trigger_s:.3f} s after "
                   f"the trigger, where the commanded stroke the ADC's position channel recorded is at {expected:.1f} % "
                   f"open: {dev:.1f} % of stroke apart, beyond the {tol:.1f} % allowed (a corrupted reply or an "
                   f"actuator off its stroke)", dev, tol, at,
                   {"reported_pct": reported_pct, "expected_pct": expected, "since_trigger_s": since_trigger_s})


def flow_mismatch(steady_flow_m3_s: float, q0_m3_s: float, rig_tolerance: float,
                  meter_accuracy: float = FLOW_METER_ACCURACY, n_readings: int = 1) -> Finding | None:
    """The steady flow the meter measured before the trigger against the rig's Q0: allowed
    ``rig_tolerance`` (the readiness check's, a fraction of Q0) plus the meter's accuracy."""
    if not (math.isfinite(steady_flow_m3_s) and q0_m3_s > 0):
        return None
    dev = abs(steady_flow_m3_s - q0_m3_s) / q0_m3_s
    tol = rig_tolerance + meter_accuracy
    if dev <= tol:
        return None
    return Finding(FLOW_MISMATCH, "flowmeter",
                   f"flow mismatch: the flowmeter's steady flow before the trigger was {steady_flow_m3_s * 1e3:.3f} "
                   f"l/s ({n_readings} readings), the rig's Q0 is {q0_m3_s * 1e3:.3f} l/s: {dev:.1%} apart, beyond the "
                   f"{tol:.1%} allowed (rig tolerance {rig_tolerance:.0%} + meter {meter_accuracy:.1%})",
                   dev, tol, None, {"steady_flow_m3_s": steady_flow_m3_s, "q0_m3_s": q0_m3_s})


def head_tolerance_m(accuracy_fs: float, full_scale_pa: float, margin_m: float = RESERVOIR_MARGIN_M) -> float:
    """The transducer's accuracy (a fraction of full scale, as head) plus the reservoir's margin."""
    return pressure_to_head_m(accuracy_fs * full_scale_pa) + margin_m


def head_mismatch(steady_head_m: float, predicted_m: float, tolerance_m: float) -> Finding | None:
    """The transducer's steady head (pretrigger mean) against the rig's predicted steady head."""
    if not (math.isfinite(steady_head_m) and math.isfinite(predicted_m)):
        return None
    dev = abs(steady_head_m - predicted_m)
    if dev <= tolerance_m:
        return None
    return Finding(HEAD_MISMATCH, "pressure",
                   f"head mismatch (warning): steady head {steady_head_m:.2f} m measured, the rig predicts "
                   f"{predicted_m:.2f} m: {dev:.2f} m apart, beyond the {tolerance_m:.2f} m allowed (transducer "
                   "accuracy + reservoir margin); check the reservoir level and the transducer's zero",
                   dev, tolerance_m, None, {"steady_head_m": steady_head_m, "predicted_m": predicted_m})


def worst(findings) -> Finding | None:
    found = [f for f in findings if f is not None]
    return max(found, key=lambda f: f.deviation - f.tolerance) if found else None


class RedundancyMonitor:
    """What one run saw of the redundant channels, fed from the acquisition and slow threads
    (append-only, under a lock), compared once at the end (``position_finding``, ``flow_finding``)."""

    def __init__(self):
        self._lock = threading.Lock()
        self._t: list = []
        self._pos: list = []
        self._polls: list = []  # (state name, position %, position is a measurement, time since trigger)
        self._flows: list = []  # OK flow readings before the trigger (m3/s)

    def adc(self, t: np.ndarray, pos: np.ndarray, quality: np.ndarray, still: bool = False) -> None:
        """An ADC block on the run's axis; flagged samples are not a position (NaN). Codes 0-2 (ok,
        over / under range: velab.drivers.blocks.QUALITY_CODES) are measurements.

        ``still``: a block from before the trigger command (the valve cannot move yet): only its
        lowest and highest samples are kept, all a comparison with a still valve needs (an armed
        wait of minutes at 10 kHz would otherwise be kept whole)."""
        t = np.asarray(t, float)
        p = np.where(np.asarray(quality) <= 2, np.asarray(pos, float), np.nan)
        if still:
            if not np.isfinite(p).any():
                return
            keep = np.unique([int(np.nanargmin(p)), int(np.nanargmax(p))])
            t, p = t[keep], p[keep]
        with self._lock:
            self._t.append(t)
            self._pos.append(p)

    def valve(self, st) -> None:
        """An actuator status (ValveStatus) as polled."""
        with self._lock:
            # over / under range is still a measurement (a bound): 128 % open is compared, and disagrees
            self._polls.append((st.state.name, float(st.position.value), st.position.quality.is_measurement,
                                float(st.time_since_trigger_s)))

    def flow(self, value_m3_s: float) -> None:
        """An OK flow reading before the trigger."""
        with self._lock:
            self._flows.append(float(value_m3_s))

    def position_finding(self, trigger_s: float | None, trigger_measured: bool,
                         profile: tuple[float, float, float] | None = None) -> tuple[Finding | None, int]:
        """The worst position disagreement of the run and the number of polls compared.

        A reply with no time since trigger or a still state (IDLE, ARMED) is compared with the baseline the ADC saw
        (before the trigger). A reply after the trigger stands at trigger + the actuator's time since
        trigger on the ADC's axis, only when the trigger instant was measured from the feedback (else the
        two axes are not tied: not compared); mid-stroke against the ADC's range over +-POSITION_TIMING_S
        around that instant and against the commanded stroke (``profile`` (beta, gamma, end),
        ``stroke_mismatch``); after the stroke against what the ADC saw from that instant on."""
        with self._lock:
            if not self._t:
                return None, 0
            t, pos, polls = np.concatenate(self._t), np.concatenate(self._pos), list(self._polls)
        base_end = trigger_s if trigger_s is not None else float(t[-1])
        placed = trigger_s is not None and trigger_measured
        out, n = [], 0
        for state, reported, ok, tst in polls:
            if not ok:
                continue  # NaN, or the actuator in FAULT: no position to compare
            if tst <= 0.0 or state in STILL:  # no stroke yet: the valve stands where the baseline shows it
                f = position_mismatch(reported, base_end, t, pos, t_span=(float(t[0]), base_end))
            elif not placed:
                continue
            elif state == "RUNNING":
                at = trigger_s + tst
                f = position_mismatch(reported, at, t, pos)
                if f is None and profile is not None:
                    f = stroke_mismatch(reported, tst, profile, trigger_s)
            else:  # the stroke is over (or stopped): the valve stands where the ADC saw it from then on
                at = trigger_s + tst
                f = position_mismatch(reported, at, t, pos, t_span=(at - POSITION_TIMING_S, float(t[-1])))
            n += 1
            out.append(f)
        return worst(out), n

    @property
    def flow_readings(self) -> int:
        """How many OK flow readings came before the trigger (0: the steady flow was not compared)."""
        with self._lock:
            return len(self._flows)

    def flow_finding(self, q0: float, rig_tolerance: float) -> Finding | None:
        with self._lock:
            flows = list(self._flows)
        if not flows:
            return None
        return flow_mismatch(float(np.mean(flows)), q0, rig_tolerance, n_readings=len(flows))
