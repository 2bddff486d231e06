"""Every injected fault ends in a typed error, a quality flag or a counted gap; never a hang or a silent wrong value."""

import errno
import math
import socket
import time

import numpy as np
import pytest

from sim_helpers import manual_sim, wait_until

from velab.drivers.base import (DeviceDisconnected, DeviceException, DeviceFault, DeviceReset, DeviceTimeout,
                                ProtocolError, Quality)
from velab.drivers.bench import open_device
from velab.drivers.valve import ValveState
from velab.simulators.bench import SimulatedBench
from velab.simulators.clock import ManualClock
from velab.simulators.faults import FaultPlan
from velab.errors import ConfigError

CONFIG = {
    "rig": "perugia", "material": "A", "clock": "manual",
    "devices": {
        "pressure_adc": {"kind": "modbus_adc", "endpoints": [{"transport": "tcp"}]},
        "valve": {"kind": "valve_actuator", "endpoints": [{"transport": "tcp"}]},
        "flowmeter": {"kind": "flowmeter", "endpoints": [{"transport": "rtu-pty"}, {"transport": "tcp"}]},
    },
}
TIMEOUT = 0.15  # the reply timeout where a test waits for a timeout (a slow, silent or mute device): errors come fast
# ... and where the device answers (soundly or with the fault under test): a loaded host (two suites at once) delayed
# a reply past 0.15 s, and on RTU that late reply then arrived glued to the retry's (the driver rejects such a pair:
# drivers/modbus.py), so a test of an exception or a CRC error failed on the timeout it did not test
SOUND_TIMEOUT = 1.0


@pytest.fixture(scope="module")
def sim():
    yield from manual_sim(CONFIG)


@pytest.fixture(autouse=True)
def clean(sim):
    yield
    for f in sim.faults.values():
        f.clear()
    for h in sim.handles.values():
        for p in h.ptys:
            p.fault("to_host", None)
            p.fault("to_device", None)
            p.pause(False)
    sim.rig.faults.clear()
    sim.rig.reset()


def connect(sim, device, transport=None, retries=1, timeout_s=TIMEOUT):
    bench = sim.bench(prefer=(transport,) if transport else None,
                      **{device: {"timeout_s": timeout_s, "retries": retries}})
    return open_device(bench.devices[device])


def bounded(fn, exc, match=None, limit=2.0):
    t0 = time.monotonic()
    with pytest.raises(exc, match=match) as ei:
        fn()
    assert time.monotonic() - t0 < limit, "the error took too long: timeouts must be bounded"
    return ei.value


def drain(fm, quiet_s: float, limit_s: float = 10.0) -> None:
    """Read ``fm``'s line until nothing has come for ``quiet_s``: the replies a slow device still owes (it answers one
    request at a time, in order) end here, not in the next test's client on the same serial line."""
    end = time.monotonic() + limit_s
    while time.monotonic() < end and fm.bus.transport.read(256, time.monotonic() + quiet_s):
        pass


@pytest.mark.parametrize("transport", ["rtu-pty", "tcp"])
def test_reply_delay_is_a_timeout(sim, transport):
    # a delay well past both attempts (2 x 0.15 s): with 0.5 s a loaded host started the retry so late that the first
    # attempt's reply landed in it -- RTU carries no transaction id, so it was taken as the flow's answer and the
    # alarm word's read then timed out twice (3 timeouts)
    delay = 1.0
    sim.faults["flowmeter"].set(delay_s=delay)
    fm = connect(sim, "flowmeter", transport)
    try:
        bounded(fm.read_flow, DeviceTimeout, "no reply.*after 2 attempts")
        assert fm.bus.stats.timeouts == 2
        sim.faults["flowmeter"].clear()
        drain(fm, quiet_s=delay + 0.2)
    finally:
        fm.close()
    fm = connect(sim, "flowmeter", transport, timeout_s=SOUND_TIMEOUT)
    try:
        assert math.isfinite(fm.read_flow().value)  # the device, its delay cleared, answers again
    finally:
        fm.close()


@pytest.mark.parametrize("transport", ["rtu-pty", "tcp"])
def test_silent_device_is_a_timeout(sim, transport):
    sim.faults["flowmeter"].set(silent=True)
    fm = connect(sim, "flowmeter", transport, retries=0)
    try:
        bounded(fm.read_flow, DeviceTimeout)
    finally:
        fm.close()


def test_exception_reply(sim):
    sim.faults["flowmeter"].set(exception_code=6)
    fm = connect(sim, "flowmeter", "rtu-pty", timeout_s=SOUND_TIMEOUT)
    try:
        e = bounded(fm.read_flow, DeviceException, "refused \\(exception 6: server device busy\\)")
        assert e.code == 6
    finally:
        fm.close()


def test_corrupted_crc_is_protocol_error_and_one_bad_reply_is_retried(sim):
    fm = connect(sim, "flowmeter", "rtu-pty", timeout_s=SOUND_TIMEOUT)
    try:
        sim.faults["flowmeter"].set(corrupt_crc=True)
        bounded(fm.read_flow, ProtocolError, "CRC error")
        sim.faults["flowmeter"].clear()
        sim.faults["flowmeter"].set(corrupt_crc=True, count=1)
        assert fm.read_flow().value == pytest.approx(sim.rig.rig.steady_flow_m3_s, rel=0.01)
        assert fm.bus.stats.protocol_errors >= 2
    finally:
        fm.close()


def test_garbled_tcp_reply_is_protocol_error(sim):
    sim.faults["valve"].set(garble=True)
    v = connect(sim, "valve")
    try:
        bounded(v.read_state, (ProtocolError, DeviceTimeout))
    finally:
        v.close()


def test_pty_byte_fault_hook_drops_a_byte(sim):
    pair = sim.handles["flowmeter"].ptys[0]
    pair.fault("to_host", lambda b: b[:-1])  # the last byte of every chunk lost on the wire
    fm = connect(sim, "flowmeter", "rtu-pty", retries=0)
    try:
        bounded(fm.read_flow, (ProtocolError, DeviceTimeout))
        pair.fault("to_host", None)
        fm.bus.timeout_s, fm.bus.retries = SOUND_TIMEOUT, 1  # the line sound again: its reply, however late
        assert fm.read_flow().quality is Quality.OK
    finally:
        fm.close()


def test_silent_line_then_back(sim):
    pair = sim.handles["flowmeter"].ptys[0]
    fm = connect(sim, "flowmeter", "rtu-pty", retries=0)
    try:
        before = pair.bytes_dropped["to_device"]
        pair.pause(True)
        bounded(fm.read_flow, DeviceTimeout)
        # the request is gone before the line comes back (a bridge thread that read it only then would carry it to
        # the device, whose reply would meet the next read)
        # one read request of 8 bytes, dropped
        assert wait_until(lambda: pair.bytes_dropped["to_device"], before + 8, timeout_s=5.0) == before + 8
        pair.pause(False)
        fm.bus.timeout_s, fm.bus.retries = SOUND_TIMEOUT, 1  # the line back: its reply, however late
        assert fm.read_flow().quality is Quality.OK
    finally:
        fm.close()


def test_disconnect_and_reconnect_tcp(sim):
    h = sim.handles["valve"]
    v = connect(sim, "valve")
    try:
        assert v.read_state() is ValveState.IDLE
        h.disconnect()
        bounded(v.read_state, DeviceDisconnected)
        h.reconnect()
        assert v.read_state() is ValveState.IDLE
        assert v.bus.stats.reconnects >= 1
    finally:
        v.close()
        if not h.servers[0].running:
            h.reconnect()


def test_a_disconnected_device_keeps_its_port(sim):
    """While down, the device's port refuses connections and is no one else's: a socket bound to it fails
    (before, the port was free for the outage, and another simulator could take it). Then it listens there again."""
    h = sim.handles["valve"]
    server = h.servers[0]
    port = server.port
    try:
        h.disconnect()
        other = socket.socket()
        try:
            with pytest.raises(OSError) as exc:
                other.bind((server.host, port))  # (no SO_REUSEADDR: TIME_WAIT of the dropped links does not matter)
        finally:
            other.close()
        assert exc.value.errno == errno.EADDRINUSE
        with pytest.raises(ConnectionRefusedError):
            socket.create_connection((server.host, port), timeout=2.0)
        h.reconnect()
        assert server.port == port
        v = connect(sim, "valve")
        try:
            assert v.read_state() is ValveState.IDLE
        finally:
            v.close()
    finally:
        if not server.running:
            h.reconnect()


def test_flow_nan_out_of_range_alarm_and_stuck(sim):
    fm = connect(sim, "flowmeter", "tcp", timeout_s=SOUND_TIMEOUT)
    try:
        sim.rig.faults.flow_nan = True
        r = fm.read_flow()
        assert math.isnan(r.value) and r.quality is Quality.NAN
        sim.rig.faults.flow_nan = False
        sim.rig.faults.flow_value = 0.5
        assert fm.read_flow().quality is Quality.OVER_RANGE
        sim.rig.faults.flow_value = None
        sim.rig.faults.flow_alarm_bits = 0b1
        assert fm.read_flow().quality is Quality.FAULT and fm.read_alarms() == ["empty pipe"]
        sim.rig.faults.flow_alarm_bits = 0
        # stuck sensor: the value stops changing; flagged once stale_after_s of host time has passed
        sim.rig.faults.flow_stuck_at = sim.clock.now()
        fm.stale_after_s = 0.05
        assert fm.read_flow().quality is Quality.OK
        sim.clock.advance(3.0)
        time.sleep(0.1)
        assert fm.read_flow().quality is Quality.STALE
    finally:
        fm.close()


def test_flowmeter_constant_zero_flow_is_not_stale(sim):
    """A closed valve gives a constant 0 (the meter's low-flow cut-off): a reading, not a stuck sensor.
    A value frozen away from zero is still flagged, and the check restarts when the flow comes back."""
    fm = connect(sim, "flowmeter", "tcp", timeout_s=SOUND_TIMEOUT)
    try:
        fm.stale_after_s = 0.05
        sim.rig.faults.flow_value = 0.0
        assert fm.read_flow().value == 0.0
        sim.clock.advance(3.0)
        time.sleep(0.1)
        r = fm.read_flow()
        assert r.value == 0.0 and r.quality is Quality.OK
        sim.rig.faults.flow_value = 0.004  # flow back, then frozen there
        assert fm.read_flow().quality is Quality.OK
        sim.clock.advance(3.0)
        time.sleep(0.1)
        assert fm.read_flow().quality is Quality.STALE
    finally:
        sim.rig.faults.flow_value = None
        fm.close()


@pytest.mark.parametrize("mA,quality", [
    (22.0, Quality.SENSOR_FAULT),  # NE43: above 20.5 mA is a transmitter fault, not a pressure
    (20.4, Quality.OVER_RANGE),  # beyond the span but inside the NE43 band: a real (bounded) value
    (3.82, Quality.UNDER_RANGE),
    (3.7, Quality.SENSOR_FAULT),
    (2.0, Quality.OPEN_LOOP),
    (float("nan"), Quality.FAULT),  # the module's "ADC failed" status bit
])
def test_adc_loop_current_quality_polled(sim, mA, quality):
    adc = connect(sim, "pressure_adc", timeout_s=SOUND_TIMEOUT)
    try:
        sim.rig.faults.channel_mA = {0: mA}
        r = adc.read_pressure()
        assert r.quality is quality and r.quality.is_measurement == (quality in (Quality.OVER_RANGE,
                                                                                 Quality.UNDER_RANGE))
    finally:
        adc.close()


@pytest.mark.parametrize("mA,quality", [(22.0, Quality.SENSOR_FAULT), (2.0, Quality.OPEN_LOOP),
                                        (float("nan"), Quality.OPEN_LOOP), (20.4, Quality.OVER_RANGE)])
def test_adc_loop_current_quality_buffered(sim, mA, quality):
    adc = connect(sim, "pressure_adc", timeout_s=SOUND_TIMEOUT)
    try:
        sim.rig.faults.channel_mA = {0: mA}
        adc.start_buffer()
        sim.clock.advance(0.01)
        b = adc.read_buffer()
        assert len(b) == 20 and all(b.quality_of(i, 0) is quality for i in range(len(b)))
        assert all(b.quality_of(i, 1) is Quality.OK for i in range(len(b)))
        assert b.quality[0] is quality and b.good("pressure").sum() == (20 if quality.is_measurement else 0)
    finally:
        adc.close()


def test_adc_stuck_sensor_is_flagged_stale(sim):
    adc = connect(sim, "pressure_adc", timeout_s=SOUND_TIMEOUT)
    try:
        adc.start_buffer()
        sim.clock.advance(0.05)
        assert (adc.read_buffer().sample_quality[:, 0] == 0).all()
        sim.rig.faults.stuck_channels = {0: sim.clock.now()}
        sim.clock.advance(0.2)
        b = adc.read_buffer()
        q = [b.quality_of(i, 0) for i in range(len(b))]
        assert q[-1] is Quality.STALE and q.count(Quality.STALE) >= len(b) - 201
        assert all(b.quality_of(i, 1) is Quality.OK for i in range(len(b)))
    finally:
        adc.close()


def test_adc_counter_going_back_is_a_device_reset(sim):
    adc, other = (connect(sim, "pressure_adc", timeout_s=SOUND_TIMEOUT) for _ in range(2))
    try:
        adc.start_buffer()
        sim.clock.advance(0.1)
        assert adc.read_buffer().n == 200
        other.start_buffer()  # someone restarts the module's acquisition: its counter goes back to 0
        sim.clock.advance(0.01)
        e = bounded(adc.read_buffer, DeviceReset, "sample counter went back from 200 to 20")
        assert e.device == "pressure_adc" and e.reason == "reset"
        adc.attach_buffer()  # re-attaching explicitly resumes from the new counter
        sim.clock.advance(0.01)
        assert adc.read_buffer().n == 20
    finally:
        adc.close()
        other.close()


def test_unnamed_flow_alarm_bit_is_a_fault_not_ignored(sim):
    fm = connect(sim, "flowmeter", "tcp", timeout_s=SOUND_TIMEOUT)
    try:
        sim.rig.faults.flow_alarm_bits = 1 << 7  # a bit the profile does not name
        assert fm.read_flow().quality is Quality.FAULT and fm.read_alarms() == ["bit 7"]
    finally:
        fm.close()


def test_adc_overrun_is_a_counted_gap_not_invented_samples(sim):
    adc = connect(sim, "pressure_adc", timeout_s=SOUND_TIMEOUT)
    try:
        adc.start_buffer()
        sim.clock.advance(0.1)
        b1 = adc.read_buffer()
        cap = adc._cap
        sim.clock.advance(3 * cap / 2000.0)  # the reader stalled for three buffer lengths
        b2 = adc.read_buffer()
        assert b2.lost_before > 0 and adc.stats.overruns == 1
        assert b1.index[-1] + 1 + b2.lost_before == b2.index[0]
        assert adc.stats.samples + adc.stats.lost == b2.index[-1] + 1
        assert adc.stats.gaps == [(b1.index[-1] + 1, b2.lost_before)]
        truth = sim.rig.pressure_pa(b2.device_time_s)  # what is returned is right, sample for sample
        assert np.max(np.abs(b2.column("pressure") - truth)) < 20.0
    finally:
        adc.close()


def test_valve_fault_during_manoeuvre(sim):
    sim.rig.faults.valve_fault_after_s = 0.1
    v = connect(sim, "valve", timeout_s=SOUND_TIMEOUT)
    try:
        v.set_manoeuvre(32.0, -5.5)
        v.arm()
        v.trigger()
        sim.clock.advance(0.05)
        assert v.check().state is ValveState.RUNNING
        sim.clock.advance(0.5)
        e = bounded(lambda: v.wait_for({ValveState.DONE}, timeout_s=0.5), DeviceFault, "following error")
        s = v.read_status()
        assert s.state is ValveState.FAULT and s.position.quality is Quality.FAULT
        stuck_at = s.position.value
        assert 60 < stuck_at < 100  # seized at tau = 0.1 s: opening 1/(1+exp(3.2-5.5)) ~ 91 %
        with pytest.raises(DeviceFault):
            v.check()
        bounded(v.arm, DeviceException, "exception 4")
        # the pressure follows the seized valve: no further closure, bounded surge
        t = sim.rig.trigger_time + np.array([0.1, 2.0])
        assert sim.rig.valve_position(t) == pytest.approx([stuck_at, stuck_at], abs=0.01)
        v.reset()
        assert v.read_state() is ValveState.IDLE
    finally:
        v.close()


def test_wait_for_times_out(sim):
    v = connect(sim, "valve", timeout_s=SOUND_TIMEOUT)
    try:
        v.arm()
        bounded(lambda: v.wait_for({ValveState.DONE}, timeout_s=0.1), DeviceTimeout, "still ARMED")
    finally:
        v.close()


def test_fault_plan_from_config():
    plan = FaultPlan.from_dict({"flowmeter": {"exception_code": 6, "count": 2},
                                "rig": {"flow_nan": True, "stuck_channels": {"0": 1.5}}})
    cfg = dict(CONFIG, faults={"flowmeter": {"exception_code": 6, "count": 2}, "rig": {"stuck_channels": {"0": 1.5}}})
    s = SimulatedBench(cfg, clock=ManualClock(), ephemeral=True)
    assert s.faults["flowmeter"].exception_code == 6 and s.faults["flowmeter"].count == 2
    assert s.rig.faults.stuck_channels == {0: 1.5}
    assert plan.rig["flow_nan"] is True
    with pytest.raises(ConfigError, match="unknown device fault"):
        FaultPlan.from_dict({"flowmeter": {"explode": True}})
    with pytest.raises(ConfigError, match="no such simulated device"):
        SimulatedBench(dict(CONFIG, faults={"nosuch": {"silent": True}}), clock=ManualClock(), ephemeral=True)
