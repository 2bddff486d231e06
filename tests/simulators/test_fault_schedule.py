"""Faults at any instant of a run (before arm, at arm, at trigger, mid-record), from config and at
run time: each starts and ends at its instant on the simulation clock, over real sockets and ptys,
and the drivers name it (a typed error, a per-sample quality, an exactly counted gap)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim_helpers import manual_sim

from velab.drivers.base import (ChecksumError, DeviceDisconnected, DeviceException, DeviceTimeout, FrameError,
                                ProtocolError, Quality, ReplyMismatch, TriggerNotStarted)
from velab.drivers.bench import open_device
from velab.drivers.valve import ValveState
from velab.errors import ConfigError
from velab.simulators.bench import SimulatedBench
from velab.simulators.clock import ManualClock

pytestmark = pytest.mark.timeout(120)

CONFIG = {
    "rig": "perugia", "material": "A", "clock": "manual",
    "devices": {
        "pressure_adc": {"kind": "modbus_adc", "sample_rate_hz": 2000, "buffer_channels": 2,
                         "endpoints": [{"transport": "tcp"}]},
        "valve": {"kind": "valve_actuator", "endpoints": [{"transport": "tcp"}]},
        "flowmeter": {"kind": "flowmeter", "endpoints": [{"transport": "rtu-pty"}, {"transport": "tcp"}]},
    },
}
# A sound reply's wait: the simulated devices answer from this process's threads, which a loaded 2-core host
# kept past 0.25 s (the stuck-position test's reads; two other tests had been raised to 1 s one by one for the
# same reason); the manual clock does not move meanwhile, so a long wait changes no outcome, it only costs time
# where a timeout is the outcome (the silent and the lost-reply tests).
TIMEOUT = 2.0
# The late-reply test's own: its reply, delayed LATE_REPLY_S, must miss this timeout and come while the next
# request is being answered.
SHORT_TIMEOUT = 0.25
LATE_REPLY_S = 0.6


@pytest.fixture(scope="module")
def sim():
    yield from manual_sim(CONFIG)


@pytest.fixture(autouse=True)
def clean(sim):
    yield
    sim.clear_fault()
    sim.poll_faults()
    sim.rig.reset()
    # the next test's anchors are its own run's: a test that set the clock back below an earlier test's
    # trigger would otherwise find that trigger "after" its fault was scheduled (seen with -n 2)
    sim.instants.clear()


def connect(sim, device, transport=None, retries=0, timeout_s=TIMEOUT):
    bench = sim.bench(prefer=(transport,) if transport else None,
                      **{device: {"timeout_s": timeout_s, "retries": retries}})
    return open_device(bench.devices[device])


def run_to_trigger(sim, valve):
    """ARM, then TRIGGER 1 s later, through the actuator's Modbus interface (what the rig observes)."""
    valve.set_manoeuvre(32.0, -5.5)
    valve.arm()
    sim.clock.advance(1.0)
    valve.trigger()
    return sim.rig.trigger_time


def works(fn) -> bool | type:
    try:
        fn()
        return True
    except (DeviceTimeout, ProtocolError, DeviceException, DeviceDisconnected) as exc:
        return type(exc)


# ---------------------------------------------------------------- config: one-line errors

BAD_SCHEDULES = [
    ({"device": "nosuch", "fault": {"silent": True}, "at": "trigger"}, "device: no simulated device 'nosuch'"),
    ({"device": "flowmeter", "fault": {"explode": True}, "at": "trigger"}, "fault 'explode' is not a modbus fault"),
    ({"device": "flowmeter", "fault": {"silent": 1}, "at": "trigger"}, "fault silent = 1: must be true or false"),
    ({"device": "valve", "fault": {"writes_only": True, "count": 1}, "at": "arm"}, "only qualify a fault: name one"),
    ({"device": "flowmeter", "fault": {"exception_code": 7}, "at": "arm"}, "must be a Modbus exception code"),
    ({"device": "flowmeter", "fault": {}, "at": "arm"}, "fault must be a non-empty table"),
    ({"device": "flowmeter", "fault": {"silent": True}, "at": "trigger-1"}, "'trigger-1' is not an instant"),
    ({"device": "flowmeter", "fault": {"silent": True}, "at": "now"}, "'now' is only for faults scheduled at run time"),
    ({"device": "flowmeter", "fault": {"silent": True}, "at": -2}, "must be a time >= 0 s"),
    ({"device": "flowmeter", "fault": {"silent": True}, "at": "arm", "duration_s": 0}, "duration_s = 0: must be"),
    ({"device": "flowmeter", "fault": {"silent": True}, "at": "arm", "when": 1}, "when: unknown key"),
    ({"device": "flowmeter", "fault": {"silent": True}}, "at: missing key"),
    ({"device": "rig", "fault": {"channel_mA": {"7": 22.0}}, "at": "arm"}, "channel 7 is not 0..3"),
    ({"device": "rig", "fault": {"valve_fault_bits": 2}, "at": "arm"}, "valve_fault_bits needs valve_seize"),
    ({"device": "rig", "fault": {"silent": True}, "at": "arm"}, "fault 'silent' is not a rig fault"),
]


@pytest.mark.parametrize("entry,match", BAD_SCHEDULES, ids=[m for _, m in BAD_SCHEDULES])
def test_schedule_config_errors_are_one_line(entry, match):
    cfg = dict(CONFIG, faults={"schedule": [entry]})
    with pytest.raises(ConfigError, match=match.replace("(", "\\(").replace(")", "\\)")) as ei:
        SimulatedBench(cfg, clock=ManualClock(), ephemeral=True, path="sim.toml")
    msg = str(ei.value)
    assert "\n" not in msg and msg.startswith("sim.toml: [faults].schedule #1")


def test_schedule_must_be_an_array_and_api_errors(sim):
    with pytest.raises(ConfigError, match="must be an array of tables"):
        SimulatedBench(dict(CONFIG, faults={"schedule": {"device": "valve"}}), clock=ManualClock(), ephemeral=True)
    with pytest.raises(ConfigError, match="no simulated device 'pump'"):
        sim.schedule_fault("pump", silent=True)
    with pytest.raises(ConfigError, match="'at trigger' is not an instant"):
        sim.schedule_fault("valve", at="at trigger", silent=True)
    with pytest.raises(ConfigError, match="duration_s = -1"):
        sim.schedule_fault("valve", duration_s=-1, silent=True)
    with pytest.raises(ConfigError, match="'corrupt' is not a modbus fault"):
        sim.set_fault("valve", corrupt=True)


def test_config_schedule_is_loaded():
    cfg = dict(CONFIG, faults={"schedule": [
        {"device": "flowmeter", "fault": {"silent": True}, "at": "trigger+1.5", "duration_s": 0.5},
        {"device": "rig", "fault": {"channel_mA": {"0": float("nan")}}, "at": 2.0, "every": True}]})
    s = SimulatedBench(cfg, clock=ManualClock(), ephemeral=True)
    e1, e2 = s.schedule.entries()
    assert e1.describe() == "flowmeter: silent=True at trigger+1.5 for 0.5 s"
    assert e2.fault == {"channel_mA": {0: math.nan}} or math.isnan(e2.fault["channel_mA"][0])
    assert str(e2.at) == "start+2" and e2.every


# ---------------------------------------------------------------- Modbus protocol faults at instants

@pytest.mark.parametrize("transport", ["rtu-pty", "tcp"])
def test_silent_mid_record_starts_and_ends_at_its_instant(sim, transport):
    sim.schedule_fault("flowmeter", at="trigger+1.0", duration_s=0.5, silent=True)
    fm, v = connect(sim, "flowmeter", transport), connect(sim, "valve", retries=1)
    try:
        assert works(fm.read_flow) is True  # before arm
        t0 = run_to_trigger(sim, v)
        sim.clock.set(t0 + 0.999)
        assert works(fm.read_flow) is True
        sim.clock.set(t0 + 1.0)
        assert works(fm.read_flow) is DeviceTimeout
        sim.clock.set(t0 + 1.499)
        assert works(fm.read_flow) is DeviceTimeout
        sim.clock.set(t0 + 1.5)
        assert works(fm.read_flow) is True
    finally:
        fm.close()
        v.close()


@pytest.mark.parametrize("transport", ["tcp", "rtu-pty"])
def test_lost_reply_is_carried_out_lost_request_is_not(sim, transport):
    """drop_reply: the actuator carries TRIGGER out and the reply is lost (anchored at the trigger instant,
    which that very TRIGGER makes); drop_request (writes only, once): TRIGGER never arrives, polls go on."""
    v = connect(sim, "valve", transport, retries=1)
    try:
        n0 = sim.rig.trigger_count
        sim.clock.advance(0.5)  # after any earlier trigger: "at trigger" is the next one
        sim.schedule_fault("valve", at="trigger", drop_reply=True, count=1)
        v.set_manoeuvre(32.0, -5.5)
        v.arm()
        sim.clock.advance(1.0)
        out = v.trigger()  # the reply is lost: the driver reads the state back
        assert out.started and out.readback and isinstance(out.lost_reply, DeviceTimeout)
        assert sim.rig.trigger_count == n0 + 1 and sim.rig.state() is ValveState.RUNNING
        assert v.read_status().state is ValveState.RUNNING  # count 1: the next replies come again
        sim.clear_fault()
        sim.rig.reset()
        v.reset()
        sim.schedule_fault("valve", at="arm", drop_request=True, writes_only=True, count=1)
        v.set_manoeuvre(32.0, -5.5)
        v.arm()
        sim.clock.advance(0.5)  # (the instants of later tests' faults are not this arm's)
        assert v.read_status().state is ValveState.ARMED  # a read: not affected
        with pytest.raises(TriggerNotStarted):
            v.trigger()
        assert sim.rig.trigger_count == n0 + 1 and sim.rig.state() is ValveState.ARMED  # the valve never moved
        assert v.trigger().started  # the next write gets through
    finally:
        v.close()


def test_exception_from_arm_until_cleared(sim):
    entry = sim.schedule_fault("flowmeter", at="arm", exception_code=6)
    fm, v = connect(sim, "flowmeter", "tcp"), connect(sim, "valve")
    try:
        assert works(fm.read_flow) is True
        v.arm()  # the actuator receives ARM: the rig marks the instant
        e = pytest.raises(DeviceException, fm.read_flow).value
        assert e.code == 6 and e.device == "flowmeter"
        sim.clock.advance(100.0)
        assert works(fm.read_flow) is DeviceException
        sim.clear_fault(entry=entry)
        assert works(fm.read_flow) is True
    finally:
        fm.close()
        v.close()


def test_fault_before_arm_at_start_offset(sim):
    now = sim.clock.now()
    sim.schedule_fault("flowmeter", at=now + 0.5, duration_s=0.25, garble=True)
    fm = connect(sim, "flowmeter", "rtu-pty")
    try:
        assert works(fm.read_flow) is True
        sim.clock.set(now + 0.5)
        assert issubclass(works(fm.read_flow), ProtocolError)
        sim.clock.set(now + 0.75)
        assert works(fm.read_flow) is True
    finally:
        fm.close()


CORRUPTIONS = [
    ({"corrupt_crc": True}, ChecksumError, "bad_crc"),
    ({"short_by": 3}, FrameError, "short_frame"),
    ({"extra_bytes": 4}, FrameError, "long_frame"),
    ({"wrong_unit": True}, ReplyMismatch, "wrong_unit"),
    ({"garble": True}, ProtocolError, None),
]


# Modbus TCP has no CRC: corrupt_crc there flips a data byte, which no protocol check can see
@pytest.mark.parametrize("transport,fault,cls,reason", [("rtu-pty", *c) for c in CORRUPTIONS]
                         + [("tcp", *c) for c in CORRUPTIONS if "corrupt_crc" not in c[0]])
def test_corrupted_replies_are_named_never_used(sim, transport, fault, cls, reason):
    sim.set_fault("flowmeter", **fault)
    fm = connect(sim, "flowmeter", transport)
    try:
        with pytest.raises(cls) as ei:
            fm.read_flow()
        if reason:
            assert ei.value.reason == reason
        assert ei.value.device == "flowmeter"
        sim.clear_fault("flowmeter")
        assert fm.read_flow().quality is Quality.OK
    finally:
        fm.close()


@pytest.mark.parametrize("transport", ["rtu-pty", "tcp"])
def test_late_reply_is_not_taken_for_the_next_request(sim, transport):
    """A reply delayed past the timeout arrives late; the next (other) request gets its own reply."""
    fm = connect(sim, "flowmeter", transport, timeout_s=SHORT_TIMEOUT)
    try:
        sim.set_fault("flowmeter", delay_s=LATE_REPLY_S, count=1)
        with pytest.raises(DeviceTimeout):
            fm.read_value("flow")  # the reply comes 0.6 s later, after the 0.25 s timeout
        fm.bus.retries = 2  # the device is busy until then: later attempts meet the late reply first
        assert fm.identify() == {"product_code": 24, "slave_id": 0x2A}  # not the late flow value
        st = fm.bus.stats
        assert st.late_replies + st.flushed_bytes > 0 or st.protocol_errors > 0
    finally:
        fm.close()


def test_disconnect_and_reconnect_at_instants(sim):
    sim.schedule_fault("valve", at="trigger+0.5", duration_s=1.0, disconnect=True)
    v = connect(sim, "valve", retries=1)
    try:
        t0 = run_to_trigger(sim, v)
        sim.clock.set(t0 + 0.5)
        sim.poll_faults()
        assert works(v.read_status) is DeviceDisconnected
        sim.clock.set(t0 + 1.5)
        sim.poll_faults()
        assert v.read_status().state in (ValveState.RUNNING, ValveState.DONE)
        assert v.bus.stats.reconnects >= 1
    finally:
        v.close()


def test_disconnect_for_good_until_cleared(sim):
    adc = connect(sim, "pressure_adc", retries=1)
    sim.schedule_fault("pressure_adc", at="now", disconnect=True)
    try:
        sim.clock.advance(1000.0)
        sim.poll_faults()
        assert works(adc.read_pressure) is DeviceDisconnected
        sim.clear_fault("pressure_adc")
        assert adc.read_pressure().quality is Quality.OK
    finally:
        adc.close()


# ---------------------------------------------------------------- rig (sensor) faults at instants

def buffered(sim, adc, seconds):
    sim.clock.advance(seconds)
    return adc.read_buffer()


@pytest.mark.parametrize("fault,quality", [
    ({"channel_mA": {0: 22.0}}, Quality.SENSOR_FAULT),  # NE43 failure-high: not a pressure ceiling
    ({"channel_mA": {0: 2.0}}, Quality.OPEN_LOOP),
    ({"channel_mA": {0: math.nan}}, Quality.OPEN_LOOP),  # a NaN burst: the module's ring has no invalid code
])
def test_sensor_fault_burst_flags_exactly_its_samples(sim, fault, quality):
    sim.schedule_fault("rig", at="trigger+0.2", duration_s=0.05, **fault)
    adc, v = connect(sim, "pressure_adc"), connect(sim, "valve")
    try:
        adc.start_buffer()
        t0 = run_to_trigger(sim, v)
        b = buffered(sim, adc, 0.5)
        t = b.device_time_s
        inside = (t >= t0 + 0.2 - 1e-9) & (t < t0 + 0.25 - 1e-9)
        assert inside.sum() == 100  # 0.05 s at 2 kHz
        codes = np.array([b.quality_of(i, 0) for i in range(b.n)])
        assert all(c is quality for c in codes[inside])
        assert all(c is Quality.OK for c in codes[~inside])
        np.testing.assert_array_equal(b.good("pressure"), ~inside)
    finally:
        adc.close()
        v.close()


def test_stuck_valve_position_feedback_is_flagged(sim):
    sim.schedule_fault("rig", at="trigger+0.05", stuck_channels=[1])
    adc, v = connect(sim, "pressure_adc"), connect(sim, "valve")
    try:
        adc.start_buffer()
        t0 = run_to_trigger(sim, v)
        b = buffered(sim, adc, 0.5)
        t = b.device_time_s
        stuck = t >= t0 + 0.05 - 1e-9
        pos = b.column("valve_position")
        assert np.ptp(pos[stuck]) == 0 and np.ptp(pos[~stuck][-50:]) > 0  # frozen while the valve moves
        q = [b.quality_of(i, 1) for i in range(b.n)]
        first_stale = q.index(Quality.STALE)
        assert t[first_stale] == pytest.approx(t0 + 0.05 + adc.stale_samples / 2000.0, abs=1.5e-3)
        assert all(x is Quality.STALE for x in q[first_stale:])
        assert all(b.quality_of(i, 0) is Quality.OK for i in range(b.n))
    finally:
        adc.close()
        v.close()


def test_flowmeter_faults_in_windows(sim):
    sim.schedule_fault("rig", at="trigger+1.0", duration_s=1.0, flow_nan=True)
    sim.schedule_fault("rig", at="trigger+3.0", duration_s=1.0, flow_alarm_bits=0b1000)
    fm, v = connect(sim, "flowmeter", "tcp"), connect(sim, "valve")
    try:
        t0 = run_to_trigger(sim, v)
        sim.clock.set(t0 + 0.99)
        assert fm.read_flow().quality is Quality.OK
        sim.clock.set(t0 + 1.0)
        assert fm.read_flow().quality is Quality.NAN
        sim.clock.set(t0 + 2.0)
        assert fm.read_flow().quality is Quality.OK
        sim.clock.set(t0 + 3.5)
        assert fm.read_flow().quality is Quality.FAULT and fm.read_alarms() == ["sensor fault"]
        sim.clock.set(t0 + 4.0)
        assert fm.read_flow().quality is Quality.OK
    finally:
        fm.close()
        v.close()


def test_valve_seizes_mid_stroke_at_its_instant(sim):
    sim.schedule_fault("rig", at="trigger+0.1", valve_seize=True, valve_fault_bits=0b10)
    v = connect(sim, "valve", retries=1)
    try:
        t0 = run_to_trigger(sim, v)
        sim.clock.set(t0 + 0.0999)
        assert v.read_status().state is ValveState.RUNNING
        sim.clock.set(t0 + 0.1)
        s = v.read_status()
        assert s.state is ValveState.FAULT and s.faults == ("drive fault",) and s.position.quality is Quality.FAULT
        stuck = s.position.value
        assert 60 < stuck < 100  # seized at tau = 0.1 s of a 32/s, -5.5 sigmoid (~91 % open)
        sim.clock.advance(2.0)
        assert v.read_status().position.value == pytest.approx(stuck)
    finally:
        v.close()


def test_valve_seize_at_run_time_mid_stroke(sim):
    v = connect(sim, "valve", retries=1)
    try:
        t0 = run_to_trigger(sim, v)
        sim.clock.set(t0 + 0.15)
        before = v.read_status().position.value
        sim.set_fault("rig", valve_seize=True)
        s = v.read_status()
        assert s.state is ValveState.FAULT and s.position.value == pytest.approx(before, abs=0.01)
        assert s.faults == ("following error",)
    finally:
        v.close()
