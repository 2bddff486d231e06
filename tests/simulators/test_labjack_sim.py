"""The LabJack driver against the simulated T7 over real sockets (Modbus TCP + the stream port), and the
simulator read by clients that are not velab's (pyModbusTCP; a raw socket decoding the stream by hand)."""

import dataclasses
import socket
import struct
import threading
import time

import numpy as np
import pytest

from velab.config import load_material, load_rig
from velab.drivers.base import DeviceDisconnected, FrameError, StreamSilent
from velab.drivers.fired_valve import DaqPosition
from velab.drivers.bench import BenchDevice
from velab.drivers.labjack import StreamFault
from velab.drivers.labjack_bench import open_labjack
from velab.drivers.base import ProfileError
from velab.simulators.clock import make_clock
from velab.simulators.labjack_device import SIM_CALIBRATION
from velab.simulators.labjack_sim import LabJackSimHandle
from velab.simulators.rig import SimulatedRig

RATE = 2000.0


@pytest.fixture(scope="module")
def rig():
    return SimulatedRig(load_rig("perugia"), load_material("A"), make_clock("realtime"))


@pytest.fixture
def sim(rig):
    h = LabJackSimHandle("daq", rig, {}, "127.0.0.1")
    h.start()
    yield h
    h.stop()


def connect(sim, **over):
    return open_labjack(BenchDevice("daq", "labjack", None, {**sim.bench_settings(), "timeout_s": 2.0, **over}))


@pytest.fixture
def lj(sim):
    d = connect(sim, data_s=3.0)
    yield d
    d.close()


def collect(lj, scans, deadline_s=20.0):
    blocks, n, end = [], 0, time.monotonic() + deadline_s
    while n < scans and time.monotonic() < end:
        b = lj.get_block(timeout=5.0)
        blocks.append(b)
        n += b.n
    return blocks


def wait_error(lj, cls, deadline_s=20.0):
    end = time.monotonic() + deadline_s
    while time.monotonic() < end:
        try:
            lj.get_block(timeout=5.0)
        except cls as exc:
            return exc
    pytest.fail(f"no {cls.__name__} within {deadline_s} s")


def test_identity_and_command_response_reads(sim, lj, rig):
    i = lj.identify()
    assert (i["model"], i["serial"], i["name"], i["calibration"]) == ("T7", 470_012_345, "velab-sim-daq", "device")
    assert np.ravel(lj.calibration.hs) == pytest.approx(np.ravel(SIM_CALIBRATION.hs), rel=1e-6)  # from its flash
    r = lj.read_analog("pressure")
    assert r.quality.value == "ok"
    assert r.value == pytest.approx(float(rig.pressure_pa(np.array([rig.clock.now()]))[0]), abs=3e3)
    assert lj.read_analog("valve_position").value == pytest.approx(100.0, abs=0.5)


def test_an_independent_modbus_client_reads_labjacks_registers(sim):
    from pyModbusTCP.client import ModbusClient as Other

    c = Other(host="127.0.0.1", port=sim.bench_settings()["port"], unit_id=1, timeout=5.0, auto_open=True)
    try:
        pid = struct.unpack(">f", struct.pack(">HH", *c.read_holding_registers(60000, 2)))[0]
        serial = struct.unpack(">I", struct.pack(">HH", *c.read_holding_registers(60028, 2)))[0]
        test = struct.unpack(">I", struct.pack(">HH", *c.read_holding_registers(55100, 2)))[0]
        name = struct.pack(">25H", *c.read_holding_registers(60500, 25)).split(b"\0")[0]
        ain0 = struct.unpack(">f", struct.pack(">HH", *c.read_holding_registers(0, 2)))[0]
    finally:
        c.close()
    assert (pid, serial, test, name) == (7.0, 470_012_345, 0x00112233, b"velab-sim-daq")
    assert 1.0 < ain0 < 5.0  # 4-20 mA through 249 ohm


def test_an_independent_host_decodes_the_stream(sim):
    """Stream set up with pyModbusTCP by the datasheet's steps, packets parsed by hand from a raw socket."""
    from pyModbusTCP.client import ModbusClient as Other

    c = Other(host="127.0.0.1", port=sim.bench_settings()["port"], unit_id=1, timeout=5.0, auto_open=True)
    f32 = lambda x: list(struct.unpack(">HH", struct.pack(">f", x)))  # noqa: E731
    u32 = lambda x: [x >> 16, x & 0xFFFF]  # noqa: E731
    s = socket.create_connection(("127.0.0.1", sim.bench_settings()["stream_port"]), timeout=5.0)
    try:
        for addr, words in ((4002, f32(1000.0)), (4004, u32(1)), (4006, u32(50)), (4016, u32(1)),
                            (4100, u32(0)), (4018, u32(0)), (4990, u32(1))):
            assert c.write_multiple_registers(addr, words), addr
        buf = b""
        packets = []
        while len(packets) < 3:
            while len(buf) < 16 or len(buf) < 6 + struct.unpack(">H", buf[4:6])[0]:
                buf += s.recv(4096)
            n = 6 + struct.unpack(">H", buf[4:6])[0]
            packets.append(buf[:n])
            buf = buf[n:]
        assert c.write_multiple_registers(4990, u32(0))
    finally:
        s.close()
        c.close()
    for i, p in enumerate(packets):
        tid, proto, length, unit, fc, kind = struct.unpack(">HHHBBB", p[:9])
        assert (tid, proto, length, unit, fc, kind) == (i, 0, 10 + 100, 1, 76, 16)
        status = struct.unpack(">H", p[12:14])[0]
        assert status == 0
        binary = np.frombuffer(p[16:], ">u2")
        volts = SIM_CALIBRATION.volts(binary)
        assert ((volts > 1.0) & (volts < 5.0)).all()  # the pressure loop, 4-20 mA x 249 ohm


def test_stream_decode_and_rate(sim, lj, rig):
    rate = lj.configure(RATE, ["pressure", "valve_position"])
    assert rate == RATE  # 500 us: a whole number of 0.1 us steps
    lj.start()
    t0 = sim.lj._session.t0
    blocks = collect(lj, 3000)
    latest = lj.latest("pressure")
    lj.stop()
    assert lj.latest("pressure") is None  # not streaming
    index = np.concatenate([b.index for b in blocks])
    assert index[0] == 0 and (np.diff(index) == 1).all() and sum(b.lost_before for b in blocks) == 0
    values = np.concatenate([b.values for b in blocks])
    want = rig.pressure_pa(t0 + index / rate)
    assert np.abs(values[:, 0] - want).max() < 150.0  # a 16-bit code is ~96 Pa on this loop
    assert np.abs(values[:, 1] - 100.0).max() < 0.5
    assert all(b.quality[0].value == "ok" and b.sample_quality.shape == b.raw.shape for b in blocks)
    assert latest is not None and latest.units == "Pa" and latest.quality.value == "ok"
    with pytest.raises(Exception, match="while streaming"):
        lj.start()
        try:
            lj.read_analog("pressure")
        finally:
            lj.stop()


def test_digital_output_reaches_the_valve_callback(sim, lj):
    got = []
    sim.on_digital = lambda line, level, t: got.append((line, level))
    lj.fire_valve()
    assert got == [(0, True)]
    assert lj.read_digital()[0] is True
    lj.write_digital(0, False)
    assert got[-1] == (0, False) and lj.read_digital()[0] is False


def _device_default_buffer(lj) -> None:
    """The T7's own default FIFO (STREAM_BUFFER_SIZE_BYTES = 0: 4096 bytes), not the profile's 32768: the overflow
    tests hold packets for a time that fills the small one."""
    lj.profile = dataclasses.replace(lj.profile, buffer_size_bytes=0)


def test_overflow_is_auto_recovered_with_the_skipped_scans_counted(sim, lj):
    _device_default_buffer(lj)
    lj.configure(RATE, ["pressure", "valve_position"])
    lj.start()
    collect(lj, 200)
    sim.stream_faults.hold_s = 1.2  # the network holds packets: 4096-byte FIFO = 1024 scans = 0.51 s
    blocks = collect(lj, 3000)
    lj.stop()
    lost = [b for b in blocks if b.lost_before]
    assert lj.stats.auto_recoveries == 1 and len(lost) == 1 and lost[0].overrun
    assert lost[0].lost_before == lj.stats.lost > 0
    index = np.concatenate([b.index for b in blocks])
    assert (np.diff(index) >= 1).all()
    assert int(np.diff(index).max()) == lost[0].lost_before + 1


def test_overflow_without_auto_recovery_is_a_named_fault(sim, lj):
    _device_default_buffer(lj)
    lj.configure(RATE, ["pressure", "valve_position"])
    lj.bus.write_registers(4028, [0, 1])  # STREAM_AUTORECOVER_DISABLE
    lj.start()
    sim.stream_faults.hold_s = 1.2
    exc = wait_error(lj, StreamFault)
    assert exc.status_name == "STREAM_BUFFER_FULL" and lj.error is exc
    lj.stop()
    lj.bus.write_registers(4028, [0, 0])


def test_scan_overlap_is_a_named_fault(sim, lj):
    lj.configure(RATE, ["pressure"])
    lj.start()
    sim.stream_faults.scan_overlap = True
    assert wait_error(lj, StreamFault).status_name == "STREAM_SCAN_OVERLAP"
    lj.stop()


def test_a_stalled_stream_is_stream_silent(sim):
    lj = connect(sim, data_s=1.0)
    try:
        lj.configure(RATE, ["pressure"])
        lj.start()
        collect(lj, 100)
        sim.stream_faults.stall = True
        assert "no stream packet" in str(wait_error(lj, StreamSilent))
        lj.stop()
    finally:
        lj.close()


def test_packets_made_before_the_host_connection_is_accepted_are_sent_once_it_is(rig, monkeypatch):
    """The simulated T7 made its first packet while the host's 702 connection waited in the listener's backlog
    (its accept thread not yet run: a loaded host); that packet went out once the connection was accepted, and
    the ones after it (they were held for good: the stream silent, StreamSilent, then the fired valve's position
    read refused by the streaming device, "read holding 2+2 refused (exception 4)")."""
    gate = threading.Event()
    accept = LabJackSimHandle._accept
    monkeypatch.setattr(LabJackSimHandle, "_accept", lambda self: (gate.wait(10.0), accept(self)))
    h = LabJackSimHandle("daq", rig, {}, "127.0.0.1")
    h.start()
    lj = connect(h, data_s=5.0)
    try:
        lj.configure(RATE, ["pressure", "valve_position"])
        lj.start()
        end = time.monotonic() + 10.0
        while not (h.lj._session is not None and h.lj._session.outgoing) and time.monotonic() < end:
            time.sleep(0.005)
        assert h.lj.client is None and h.lj._session.outgoing  # a packet made, no host connection yet
        gate.set()
        blocks = collect(lj, 2000)
        assert blocks[0].first_index == 0 and all(b.lost_before == 0 for b in blocks)
        lj.stop()
    finally:
        gate.set()
        lj.close()
        h.stop()


def test_a_position_read_after_the_stream_failed_is_the_streams_error(sim):
    """While the stream is enabled the device refuses command-response AIN reads: once its reader has ended on
    a fatal error, a read of the valve position (the fired valve's DaqPosition) raises that error, named, and
    sends nothing the device would refuse; after stop() the command-response read works again."""
    lj = connect(sim, data_s=1.0)
    try:
        lj.configure(RATE, ["pressure", "valve_position"])
        lj.start()
        collect(lj, 100)
        sim.stream_faults.stall = True
        wait_error(lj, StreamSilent)
        requests = lj.bus.stats.requests
        with pytest.raises(StreamSilent, match="valve_position: no reading: the stream .* ended: .*no stream packet"):
            DaqPosition(lj, "valve_position").read()
        assert lj.bus.stats.requests == requests
        lj.stop()
        sim.stream_faults.stall = False
        assert DaqPosition(lj, "valve_position").read().value == pytest.approx(100.0, abs=0.5)
    finally:
        lj.close()


def test_a_dropped_stream_connection_is_disconnected(sim, lj):
    lj.configure(RATE, ["pressure"])
    lj.start()
    collect(lj, 100)
    sim.disconnect_stream()
    assert "stream connection lost" in str(wait_error(lj, DeviceDisconnected))
    lj.stop()


def test_a_garbled_packet_is_a_frame_error(sim, lj):
    lj.configure(RATE, ["pressure"])
    lj.start()
    sim.stream_faults.garble = True
    assert wait_error(lj, FrameError).reason == "bad_header"
    lj.stop()


def test_bench_keys_are_checked(sim):
    with pytest.raises(ProfileError, match="bogus"):
        connect(sim, bogus=1)
    with pytest.raises(ProfileError, match="channels.nope"):
        connect(sim, channels={"nope": {"zero_offset": 1.0}})


def test_the_pressure_source_adapter(sim, lj):
    from velab.drivers.pressure_source import pressure_source

    src = pressure_source(lj, "daq")
    assert src.channels() == ("pressure", "valve_position") and src.pressure_channels() == ("pressure",)
    look = src.spot_heads(RATE, ("pressure",))
    assert look["pressure"][1] == "ok" and look["pressure"][0] > 0
    assert src.configure(RATE) == RATE and src.start() == RATE
    got = 0
    end = time.monotonic() + 20
    while got < 500 and time.monotonic() < end:
        got += sum(b.n for b in src.read_blocks(1.0).blocks)
    src.stop()
    assert got >= 500 and "T7" in src.describe()
