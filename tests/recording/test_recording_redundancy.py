"""Redundant measurements compared (velab.recording.redundancy): pure functions, no sockets, milliseconds.

The integration over the simulated bench (a corrupted valve reply ends the run flagged) is in
tests/recording/test_record_faults.py."""

from __future__ import annotations

import numpy as np
import pytest

from velab.drivers.base import Quality, Reading, pressure_to_head_m
from velab.drivers.valve import ValveState, ValveStatus
from velab.recording.redundancy import (
    FLOW_METER_ACCURACY, POSITION_ACCURACY_PCT, POSITION_TIMING_S, RESERVOIR_MARGIN_M, RedundancyMonitor, adc_range,
    flow_mismatch, head_mismatch, head_tolerance_m, position_mismatch)

FS = 2000.0
BETA, GAMMA = 32.0, -5.5  # the reference rig's closure: 90 % -> 10 % in 0.14 s


def stroke(t, t0=0.0):
    """The commanded sigmoid in position, % open, trigger at t0."""
    return 100.0 / (1.0 + np.exp(np.clip(BETA * (t - t0) + GAMMA, -50, 50)))


T = np.arange(-0.5, 1.0, 1.0 / FS)
POS = stroke(T)


def status(state, pct, tst, quality=Quality.OK):
    return ValveStatus(ValveState[state], Reading(pct, "%", 0.0, quality), (), tst, 1 if tst else 0)


# ---------------------------------------------------------------- the ADC's range over an interval
def test_adc_range_interpolates_the_ends_on_the_sample_axis():
    t = np.array([0.0, 1.0, 2.0, 3.0])
    p = np.array([100.0, 80.0, 40.0, 40.0])
    assert adc_range(t, p, 0.5, 1.5) == (60.0, 90.0)  # no sample at the ends: both interpolated
    assert adc_range(t, p, 1.0, 1.0) == (80.0, 80.0)


def test_adc_range_gives_no_verdict_without_data_near_the_interval():
    t = np.arange(0.0, 1.0, 0.01)
    p = np.full(t.size, 100.0)
    assert adc_range(t, p, 5.0, 5.1) is None  # after the record
    p[40:80] = np.nan  # flagged samples (a stuck or open-loop feedback): not a position
    assert adc_range(t, p, 0.55, 0.6) is None
    assert adc_range(t, p, 0.3, 0.35) == (100.0, 100.0)


# ---------------------------------------------------------------- position
def test_a_still_valve_agrees_within_the_accuracy_and_a_wrong_reply_is_named():
    assert position_mismatch(100.0 - 0.9 * POSITION_ACCURACY_PCT, -0.2, T, POS) is None
    f = position_mismatch(50.0, -0.2, T, POS)  # 100 % open ^ 0x0080 in the float's high word
    assert f is not None and f.kind == "position_mismatch" and f.role == "valve"
    assert f.deviation == pytest.approx(50.0, abs=0.1) and f.tolerance == POSITION_ACCURACY_PCT
    assert "50.0 % open" in f.message and "100.0 % open" in f.message


def test_mid_stroke_the_valve_may_move_between_the_two_sample_instants():
    """At the stroke's fastest (800 %/s) the ADC changes by 16 % over +-20 ms: a reply stamped
    10 ms off is in, one stamped 60 ms off is not (the allowance comes from the ADC channel itself)."""
    t_mid = -GAMMA / BETA
    late = float(stroke(np.array([t_mid + 0.010]))[0])
    assert abs(late - float(stroke(np.array([t_mid]))[0])) > POSITION_ACCURACY_PCT  # a fixed tolerance would fail
    assert position_mismatch(late, t_mid, T, POS) is None
    far = float(stroke(np.array([t_mid + 0.060]))[0])
    f = position_mismatch(far, t_mid, T, POS)
    assert f is not None and f.at_s == pytest.approx(t_mid)
    lo, hi = f.extras["adc_lo_pct"], f.extras["adc_hi_pct"]
    assert hi - lo == pytest.approx(float(stroke(np.array([t_mid - POSITION_TIMING_S]))[0]
                                          - stroke(np.array([t_mid + POSITION_TIMING_S]))[0]), rel=1e-3)


def test_a_nan_reply_is_left_to_the_drivers_quality():
    assert position_mismatch(float("nan"), 0.0, T, POS) is None


# ---------------------------------------------------------------- flow, head
def test_flow_beyond_the_rig_tolerance_plus_the_meter_accuracy():
    q0 = 3.64e-3
    assert flow_mismatch(q0 * (1 + 0.05 + 0.9 * FLOW_METER_ACCURACY), q0, 0.05) is None
    f = flow_mismatch(q0 * 0.93, q0, 0.05, n_readings=4)
    assert f is not None and f.kind == "flow_mismatch" and f.role == "flowmeter"
    assert f.deviation == pytest.approx(0.07) and f.tolerance == pytest.approx(0.05 + FLOW_METER_ACCURACY)
    assert "4 readings" in f.message


def test_head_tolerance_is_the_transducer_accuracy_plus_the_reservoir_margin():
    tol = head_tolerance_m(0.0015, 6.0e5)
    assert tol == pytest.approx(pressure_to_head_m(900.0) + RESERVOIR_MARGIN_M)
    assert head_mismatch(34.5 + 0.9 * tol, 34.5, tol) is None
    f = head_mismatch(33.0, 34.5, tol)
    assert f is not None and f.kind == "head_mismatch" and f.role == "pressure" and "warning" in f.message
    assert head_mismatch(float("nan"), 34.5, tol) is None


# ---------------------------------------------------------------- the run's monitor
def monitor_with_stroke(block=128):
    """Blocks as the acquisition thread hands them over; those before the trigger command (t < 0)
    are 'still': reduced to their extremes."""
    m = RedundancyMonitor()
    for i in range(0, T.size, block):
        j = min(i + block, T.size)
        m.adc(T[i:j], POS[i:j], np.zeros(j - i, np.uint8), still=T[j - 1] < 0)
    return m


def test_a_still_baseline_is_kept_as_its_extremes_and_still_compared():
    m = monitor_with_stroke()
    assert sum(a.size for a in m._t) <= T.size - 7 * (128 - 2)  # 7 blocks before t = 0: 2 samples each at most
    m.valve(status("ARMED", 100.0, 0.0))
    assert m.position_finding(0.0, True) == (None, 1)
    m.valve(status("ARMED", 90.0, 0.0))
    f, n = m.position_finding(0.0, True)
    assert n == 2 and f.deviation == pytest.approx(100.0 / (1 + np.exp(GAMMA)) - 90.0, abs=0.01)


def test_the_monitor_names_the_worst_disagreement_once():
    m = monitor_with_stroke()
    m.valve(status("ARMED", 100.0, 0.0))
    t1, t2 = 0.15, 0.20
    m.valve(status("RUNNING", float(stroke(np.array([t1]))[0]), t1))  # right
    m.valve(status("RUNNING", float(stroke(np.array([t2]))[0]) * 2.0, t2))  # doubled: corrupted reply
    m.valve(status("ARMED", 95.0, 0.0))  # before the trigger, 5 % off the still valve: a smaller disagreement
    f, n = m.position_finding(trigger_s=0.0, trigger_measured=True)
    assert n == 4 and f.at_s == pytest.approx(t2) and f.deviation > 10.0


def test_the_monitor_skips_what_it_cannot_place_or_trust():
    m = monitor_with_stroke()
    m.valve(status("RUNNING", 3.0, 0.15))  # mid-stroke, but the trigger was not measured: the axes are not tied
    m.valve(status("ARMED", 20.0, 0.0, Quality.FAULT))  # flagged by the driver already
    assert m.position_finding(trigger_s=0.0, trigger_measured=False) == (None, 0)
    assert m.position_finding(trigger_s=0.0, trigger_measured=True)[0] is not None


def test_a_still_state_is_still_whatever_its_time_since_trigger():
    """An actuator may keep its last run's time since trigger until the next trigger: an ARMED reply with
    one is the still valve (compared with the baseline), not a reply placed 2.5 s into this run's stroke."""
    m = monitor_with_stroke()
    m.valve(status("ARMED", 100.0, 2.5))
    f, n = m.position_finding(trigger_s=0.0, trigger_measured=True)
    assert n == 1 and f is None
    m.valve(status("IDLE", 60.0, 2.5))  # the same, 40 % off the still valve: named at the baseline's end
    f, n = m.position_finding(trigger_s=0.0, trigger_measured=True)
    assert n == 2 and f is not None and f.deviation == pytest.approx(100.0 / (1 + np.exp(GAMMA)) - 60.0, abs=0.01)


def test_flagged_adc_samples_are_no_position():
    m = RedundancyMonitor()
    m.adc(T, np.full(T.size, 50.0), np.full(T.size, 6, np.uint8))  # a stuck feedback: stale
    m.valve(status("ARMED", 100.0, 0.0))
    assert m.position_finding(0.0, True) == (None, 1)


def test_the_steady_flow_is_the_mean_of_the_readings_before_the_trigger():
    m = RedundancyMonitor()
    assert m.flow_finding(3.64e-3, 0.05) is None and m.flow_readings == 0  # no reading: no verdict (a note)
    for q in (3.30e-3, 3.31e-3, 3.29e-3):
        m.flow(q)
    f = m.flow_finding(3.64e-3, 0.05)
    assert m.flow_readings == 3
    assert f is not None and f.extras["steady_flow_m3_s"] == pytest.approx(3.30e-3) and "3 readings" in f.message


def test_an_over_range_reply_is_a_bound_and_still_compared():
    """A flipped exponent bit can make 64 % open read 128 %: the driver says over range (a
    measurement, a bound), which alone flags nothing; the comparison does."""
    m = monitor_with_stroke()
    m.valve(status("RUNNING", 128.0, 0.16, Quality.OVER_RANGE))
    f, n = m.position_finding(0.0, True)
    assert n == 1 and f is not None and f.extras["reported_pct"] == 128.0


def test_a_running_reply_is_compared_with_the_commanded_stroke_at_its_own_time_stamp():
    """velab.recording.redundancy.stroke_mismatch: no host timing enters, so a mid-stroke reply the host
    cannot place is still checked; a real actuator's following lag is allowed."""
    from velab.recording.redundancy import stroke_mismatch
    from velab.valvelaw import commanded_position_pct

    profile = (2.0, -5.5, 0.0)  # a slow closure: the stroke moves about 50 %/s mid-way
    for tst in (1.5, 2.75, 4.0):
        true = float(commanded_position_pct(tst, *profile))
        assert stroke_mismatch(true, tst, profile, 10.0) is None
        assert stroke_mismatch(true + 1.5, tst, profile, 10.0) is None  # within the instruments' 2 %
        lagged = float(commanded_position_pct(tst - 0.03, *profile))  # 30 ms behind its profile
        assert stroke_mismatch(lagged, tst, profile, 10.0) is None
        f = stroke_mismatch(true / 2, tst, profile, 10.0)  # the corrupted gateway's reply
        assert f is not None and f.kind == "position_mismatch" and f.deviation > f.tolerance >= 2.0
        assert f.at_s == pytest.approx(10.0 + tst) and "commanded stroke" in f.message
    assert stroke_mismatch(50.0, 0.0, profile, 10.0) is None  # no time stamp yet: nothing to compare
    assert stroke_mismatch(float("nan"), 1.0, profile, 10.0) is None
