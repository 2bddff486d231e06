"""LabJack T-series bytes on the wire, from LabJack's documents: the spontaneous stream packet (datasheet 3.2.4
"Low-Level Stream"), the Modbus TCP requests the driver sends (addresses and types of ljm_constants.json), the T7
calibration (datasheet 20.0.1), and the decoding of gaps, auto-recovery and fatal statuses."""

import struct
from dataclasses import replace

import numpy as np
import pytest

from velab.drivers import labjack_registers as ljr
from velab.drivers.base import DeviceException, FrameError, ImplausibleReply, ProtocolError, StreamSilent
from velab.drivers.labjack import SILENT_PACKETS, LabJackT, StreamFault, _Decode, auto_samples_per_packet
from velab.drivers.labjack_profile import load_profile
from velab.drivers.labjack_stream import PacketReader, StreamPacket, T7Calibration, encode_packet
from velab.drivers.modbus import ModbusClient
from velab.drivers.testing import expected_protocol


def mbap(tid: int, pdu: bytes, unit: int = 1) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


def write_req(tid, address, words):
    return mbap(tid, struct.pack(">BHHB", 16, address, len(words), 2 * len(words)) + struct.pack(f">{len(words)}H", *words))


def write_ack(tid, address, n):
    return mbap(tid, struct.pack(">BHH", 16, address, n))


def read_req(tid, address, n):
    return mbap(tid, struct.pack(">BHH", 3, address, n))


def read_rep(tid, words):
    return mbap(tid, struct.pack(">BB", 3, 2 * len(words)) + struct.pack(f">{len(words)}H", *words))


def f32(x):
    return list(struct.unpack(">HH", struct.pack(">f", x)))


def u32(x):
    return [x >> 16, x & 0xFFFF]


NOMINAL = replace(load_profile("labjack_t7"), calibration="nominal")


def driver(pairs):
    return expected_protocol(pairs)


# ------------------------------------------------------------------ the stream packet


def test_stream_packet_is_byte_exact():
    # tid 5, protocol 0, length 10 + 2 x 2, unit 1, function 76, type 16, reserved, backlog 8, status 0, info 0
    want = bytes.fromhex("0005 0000 000e 01 4c 10 00 0008 0000 0000 8000 ffff".replace(" ", ""))
    assert encode_packet(5, [0x8000, 0xFFFF], backlog_bytes=8) == want


def test_auto_recover_end_packet_carries_the_skipped_scans():
    p = encode_packet(0x1234, [1], status=2941, additional=300)
    assert p[12:14] == (2941).to_bytes(2, "big") and p[14:16] == (300).to_bytes(2, "big")
    assert p[0:2] == b"\x12\x34"


def test_packet_reader_splits_packets_across_reads():
    a, b = encode_packet(0, [1, 2, 3, 4]), encode_packet(1, [5, 6], status=2940, backlog_bytes=100)
    r = PacketReader()
    assert r.feed((a + b)[:10]) == []
    got = r.feed((a + b)[10:])
    assert [p.tid for p in got] == [0, 1]
    assert got[0].samples.tolist() == [1, 2, 3, 4]
    assert (got[1].status, got[1].backlog_bytes, got[1].samples.tolist()) == (2940, 100, [5, 6])
    assert r.pending == 0


@pytest.mark.parametrize("offset,value", [(2, 1), (7, 3), (8, 17)])  # protocol id, function, packet type
def test_packet_reader_refuses_what_is_not_a_stream_packet(offset, value):
    p = bytearray(encode_packet(0, [1, 2]))
    p[offset] = value
    with pytest.raises(FrameError) as e:
        PacketReader("lj").feed(bytes(p))
    assert e.value.reason == "bad_header"


# ------------------------------------------------------------------ calibration


def test_t7_calibration_is_the_datasheets_formula():
    cal = T7Calibration.nominal()
    ps, ns, center, _ = cal.hs[0]
    assert cal.volts([center])[0] == 0.0
    assert cal.volts([center + 1000])[0] == pytest.approx(1000 * ps)
    assert cal.volts([center - 1000])[0] == pytest.approx(1000 * ns)  # (center - b) x NSlope: negative
    v = np.array([-9.5, -1.0, 0.0, 1.0, 4.98, 9.5])
    assert np.abs(cal.volts(cal.binary(v)) - v).max() < 1.1 * ps / 2 + 1e-12  # within half a code


def test_calibration_from_erased_flash_is_refused():
    with pytest.raises(ProtocolError):
        T7Calibration.from_floats([float("nan")] * 41)
    with pytest.raises(ValueError):
        T7Calibration.nominal().volts([1], gain_index=1)  # nominal: +-10 V only


# ------------------------------------------------------------------ Modbus requests


def test_write_digital_is_fio_register_write():
    with driver([(write_req(1, 2000, [1]), write_ack(1, 2000, 1)), (write_req(2, 2003, [0]), write_ack(2, 2003, 1))]) as t:
        lj = LabJackT(ModbusClient(t, "tcp", unit=1, timeout_s=0.05, retries=0), NOMINAL)
        lj.write_digital(0, True)
        lj.write_digital(3, False)


def test_read_digital_reads_fio_state():
    with driver([(read_req(1, 2500, 1), read_rep(1, [0b101]))]) as t:
        lj = LabJackT(ModbusClient(t, "tcp", unit=1, timeout_s=0.05, retries=0), NOMINAL)
        assert lj.read_digital()[:4] == (True, False, True, False)


def test_read_analog_is_ain_float_through_the_shunt():
    # AIN1 at address 2 (FLOAT32): 2.988 V through 249 ohm = 12 mA = 50 % open
    with driver([(read_req(1, 2, 2), read_rep(1, f32(2.988)))]) as t:
        lj = LabJackT(ModbusClient(t, "tcp", unit=1, timeout_s=0.05, retries=0), NOMINAL)
        r = lj.read_analog("valve_position")
    assert r.value == pytest.approx(50.0, abs=1e-3) and r.units == "%" and r.quality.is_measurement


def test_read_analog_open_loop_is_named():
    with driver([(read_req(1, 0, 2), read_rep(1, f32(0.5)))]) as t:  # 2 mA: a broken loop
        lj = LabJackT(ModbusClient(t, "tcp", unit=1, timeout_s=0.05, retries=0), NOMINAL)
        assert lj.read_analog("pressure").quality.value == "open_loop"


def test_configure_writes_the_stream_registers_in_labjacks_order():
    spp = auto_samples_per_packet(2000.0, 2)
    writes = [(4990, u32(0)), (40000, f32(10.0)), (41000, [199]), (40002, f32(10.0)), (41001, [199]),
              (4002, f32(2000.0)), (4004, u32(2)), (4006, u32(spp)), (4008, f32(0.0)), (4010, u32(0)),
              (4012, u32(32768)), (4016, u32(1)), (4020, u32(0)), (4100, u32(0) + u32(2)), (4018, u32(0))]
    pairs = [(write_req(i + 1, a, w), write_ack(i + 1, a, len(w))) for i, (a, w) in enumerate(writes)]
    n = len(pairs) + 1
    pairs.append((read_req(n, 4002, 2), read_rep(n, f32(2000.0))))
    with driver(pairs) as t:
        lj = LabJackT(ModbusClient(t, "tcp", unit=1, timeout_s=0.05, retries=0), NOMINAL)
        assert lj.configure(2000.0) == 2000.0
    assert spp % 2 == 0 and spp <= 512


def test_configure_continues_when_the_stream_was_not_running():
    exc = mbap(1, bytes([0x90, 4]))  # STREAM_ENABLE = 0 refused: STREAM_NOT_RUNNING
    with driver([(write_req(1, 4990, u32(0)), exc)]) as t:
        lj = LabJackT(ModbusClient(t, "tcp", unit=1, timeout_s=0.05, retries=0), NOMINAL)
        with pytest.raises(AssertionError):  # the next request (AIN0_RANGE) is sent: past the refusal
            lj.configure(2000.0)


def test_open_checks_the_product_id():
    with driver([(read_req(1, 60000, 2), read_rep(1, f32(4.0)))]) as t:
        lj = LabJackT(ModbusClient(t, "tcp", unit=1, timeout_s=0.05, retries=0), NOMINAL)
        with pytest.raises(ImplausibleReply, match="PRODUCT_ID 4"):
            lj.open()


def test_calibration_is_read_from_flash():
    floats = [0.0003160, -0.0003161, 33500.0, -10.5] + [0.0000316, -0.0000316, 33500.0, -1.0] * 3
    pairs, tid = [], 0
    for i, x in enumerate(floats):
        tid += 1
        pairs.append((write_req(tid, 61810, u32(ljr.T7_CAL_FLASH_ADDRESS + 4 * i)), write_ack(tid, 61810, 2)))
        tid += 1
        pairs.append((read_req(tid, 61812, 2), read_rep(tid, f32(x))))
    prof = load_profile("labjack_t7")
    with driver(pairs) as t:
        lj = LabJackT(ModbusClient(t, "tcp", unit=1, timeout_s=0.05, retries=0), prof)
        cal = lj._read_calibration()
    assert cal.source == "device" and cal.hs[0] == pytest.approx(tuple(floats[:4]), rel=1e-6)


def test_read_analog_refused_while_streaming():
    lj = LabJackT(None, NOMINAL)
    lj._thread = type("T", (), {"is_alive": lambda self: True})()
    lj._enabled = True  # (start() wrote STREAM_ENABLE = 1)
    with pytest.raises(DeviceException, match="while streaming"):
        lj.read_analog("pressure")
    lj._thread, lj._enabled = None, False


def test_read_analog_after_the_stream_failed_raises_the_streams_error():
    """The reader ended on StreamSilent, the stream still enabled (not stopped): the device would refuse an AIN
    read, so none is sent (the bus is None here); the stream's own error is raised, naming the channel."""
    lj = LabJackT(None, NOMINAL, name="lj")
    lj._thread = type("T", (), {"is_alive": lambda self: False})()
    lj._enabled = True
    lj.error = StreamSilent("lj: no stream packet on port 702 for 1 s (40 packets so far)", device="lj")
    with pytest.raises(StreamSilent, match="^lj: valve_position: no reading: the stream .*for 1 s") as e:
        lj.read_analog("valve_position")
    assert e.value.device == "lj" and e.value is not lj.error
    lj._thread, lj._enabled = None, False


@pytest.mark.parametrize("rate, spp, channels, timeout", [
    (2000.0, 0, 2, 1.0),  # ~20 packets/s: the profile's data_s
    (1.0, 0, 2, SILENT_PACKETS * 1.0),  # one scan a packet, 1 s apart
    (100.0, 512, 2, SILENT_PACKETS * 256 / 100.0),  # 2.56 s a packet
])
def test_the_data_timeout_is_at_least_a_few_packet_intervals(rate, spp, channels, timeout):
    prof = replace(NOMINAL, samples_per_packet=spp)
    lj = LabJackT(None, prof)
    assert lj.data_timeout_s == prof.data_s  # nothing configured yet
    lj._channels, lj._rate = prof.channels[:channels], rate
    lj._spp = spp or auto_samples_per_packet(rate, channels)
    assert lj.data_timeout_s == pytest.approx(timeout)


# ------------------------------------------------------------------ decoding packets into runs


def pkt(tid, samples, status=0, info=0):
    return StreamPacket(tid, 0, status, info, np.asarray(samples, np.uint16))


def decode(packets, nch=2, spp=4):
    lj = LabJackT(None, NOMINAL, name="lj")
    return _Decode(nch, spp).blocks(packets, lj), lj


def test_contiguous_packets_make_one_run():
    runs, lj = decode([pkt(0, [1, 2, 3, 4]), pkt(1, [5, 6, 7, 8])])
    assert len(runs) == 1
    raw, first, lost, over = runs[0]
    assert raw.tolist() == [[1, 2], [3, 4], [5, 6], [7, 8]] and (first, lost, over) == (0, 0, False)


def test_a_transaction_id_gap_is_counted_exactly():
    runs, lj = decode([pkt(0, [1, 2, 3, 4]), pkt(3, [5, 6, 7, 8])])  # packets 1 and 2 lost: 2 x 4 samples
    assert [(r[1], r[2]) for r in runs] == [(0, 0), (6, 4)]
    assert lj.stats.lost_packets == 2 and lj.stats.lost == 4


def test_auto_recovery_skipped_scans_and_the_dummy_scan():
    packets = [pkt(0, [1, 2, 3, 4], status=2940), pkt(1, [5, 6, 0xFFFF, 0xFFFF], status=2941, info=10),
               pkt(2, [7, 8, 9, 10])]
    runs, lj = decode(packets)
    assert [(r[0].tolist(), r[1], r[2], r[3]) for r in runs] == [
        ([[1, 2], [3, 4], [5, 6]], 0, 0, True), ([[7, 8], [9, 10]], 13, 10, True)]
    assert lj.stats.auto_recoveries == 1 and lj.stats.lost == 10


@pytest.mark.parametrize("status,name", [(2942, "STREAM_SCAN_OVERLAP"), (2943, "STREAM_AUTO_RECOVER_END_OVERFLOW"),
                                         (2945, "STREAM_BUFFER_FULL")])
def test_fatal_statuses_are_named_faults(status, name):
    with pytest.raises(StreamFault) as e:
        decode([pkt(0, [1, 2, 3, 4]), pkt(1, [], status=status)])
    assert (e.value.status, e.value.status_name, e.value.reason) == (status, name, "fault")


def test_unknown_status_is_implausible():
    with pytest.raises(ImplausibleReply):
        decode([pkt(0, [1, 2, 3, 4], status=1234)])
