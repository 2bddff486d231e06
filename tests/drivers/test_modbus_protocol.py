"""Byte-exact Modbus frames (PyMeasure expected_protocol style): requests out, replies in, error frames."""

import struct

import pytest

from velab.drivers.base import (ChecksumError, DeviceDisconnected, DeviceException, DeviceTimeout, FrameError,
                                ProtocolError, ReplyMismatch)
from velab.drivers.flowmeter import Flowmeter
from velab.drivers.modbus import ModbusClient, WordOrder, crc16, decode_registers, encode_value
from velab.drivers.modbus_device import RangeError
from velab.drivers.testing import ExpectedProtocolTransport, Late, Trickle, expected_protocol
from velab.drivers.valve import ValveActuator


def rtu(*parts: bytes | int) -> bytes:
    body = b"".join(bytes([p]) if isinstance(p, int) else p for p in parts)
    return body + crc16(body)


def test_crc_known_vector():
    # 01 03 00 00 00 01 -> CRC 84 0A (the classic Modbus example)
    assert crc16(bytes.fromhex("010300000001")) == bytes.fromhex("840a")


def test_rtu_read_holding_exact_bytes():
    req = bytes.fromhex("02030bba0002")
    reply = rtu(2, 3, 4, bytes.fromhex("406d0000"))
    with expected_protocol([(req + crc16(req), reply)]) as t:
        bus = ModbusClient(t, "rtu", unit=2, timeout_s=0.05, retries=0)
        regs = bus.read_holding(3002, 2)
    assert regs == [0x406D, 0x0000]
    assert decode_registers(regs, "float32") == pytest.approx(3.703125)


def test_rtu_read_input_and_write_multiple_exact_bytes():
    read_req = rtu(1, 4, bytes.fromhex("00000003"))
    read_rep = rtu(1, 4, 6, bytes.fromhex("000100020003"))
    write_req = rtu(1, 0x10, bytes.fromhex("000a0002"), 4, bytes.fromhex("42000000"))
    write_rep = rtu(1, 0x10, bytes.fromhex("000a0002"))
    with expected_protocol([(read_req, read_rep), (write_req, write_rep)]) as t:
        bus = ModbusClient(t, "rtu", unit=1, timeout_s=0.05, retries=0)
        assert bus.read_input(0, 3) == [1, 2, 3]
        bus.write_registers(10, encode_value(32.0, "float32"))


def test_tcp_mbap_frames_and_transaction_ids():
    pairs = []
    for tid in (1, 2):
        req = struct.pack(">HHHB", tid, 0, 6, 3) + bytes.fromhex("030014 0005".replace(" ", ""))
        rep = struct.pack(">HHHB", tid, 0, 13, 3) + bytes([3, 10]) + bytes(10)
        pairs.append((req, rep))
    with expected_protocol(pairs) as t:
        bus = ModbusClient(t, "tcp", unit=3, timeout_s=0.05, retries=0)
        assert bus.read_holding(20, 5) == [0] * 5
        assert bus.read_holding(20, 5) == [0] * 5


def test_tcp_skips_late_reply_to_an_earlier_request():
    """tid 1 times out; its late reply arrives glued before the reply to tid 2: dropped, not used."""
    req1 = struct.pack(">HHHB", 1, 0, 6, 1) + bytes.fromhex("0300000001")
    late1 = struct.pack(">HHHB", 1, 0, 5, 1) + bytes([3, 2, 0, 9])
    req2 = struct.pack(">HHHB", 2, 0, 6, 1) + bytes.fromhex("0300000001")
    rep2 = struct.pack(">HHHB", 2, 0, 5, 1) + bytes([3, 2, 0, 42])
    with expected_protocol([(req1, Late(late1, with_next=True)), (req2, rep2)]) as t:
        bus = ModbusClient(t, "tcp", unit=1, timeout_s=0.05, retries=0)
        with pytest.raises(DeviceTimeout):
            bus.read_holding(0, 1)
        assert bus.read_holding(0, 1) == [42]
    assert bus.stats.late_replies == 1


def test_tcp_unknown_transaction_id_is_wrong_transaction():
    req = struct.pack(">HHHB", 1, 0, 6, 1) + bytes.fromhex("0300000001")
    rep = struct.pack(">HHHB", 7, 0, 5, 1) + bytes([3, 2, 0, 9])
    with expected_protocol([(req, rep)]) as t:
        with pytest.raises(ReplyMismatch, match="transaction id 7, expected 1") as ei:
            ModbusClient(t, "tcp", unit=1, timeout_s=0.05, retries=0).read_holding(0, 1)
    assert ei.value.reason == "wrong_transaction" and ei.value.device == "expected-protocol"


@pytest.mark.parametrize("code,name", [(2, "illegal data address"), (3, "illegal data value"), (6, "busy")])
def test_rtu_exception_reply_is_device_exception_not_retried(code, name):
    req = rtu(2, 3, bytes.fromhex("0bba0002"))
    with expected_protocol([(req, rtu(2, 0x83, code))]) as t:
        bus = ModbusClient(t, "rtu", unit=2, timeout_s=0.05, retries=3)
        with pytest.raises(DeviceException, match=name) as ei:
            bus.read_holding(3002, 2)
    assert ei.value.code == code and bus.stats.retries == 0


def test_tcp_exception_reply():
    req = struct.pack(">HHHB", 1, 0, 9, 3) + bytes.fromhex("10000000010200ff")
    rep = struct.pack(">HHHB", 1, 0, 3, 3) + bytes([0x90, 4])
    with expected_protocol([(req, rep)]) as t:
        with pytest.raises(DeviceException, match="exception 4") as ei:
            ModbusClient(t, "tcp", unit=3, timeout_s=0.05).write_registers(0, [255])
    assert ei.value.code == 4


def test_bad_crc_is_retried_then_protocol_error():
    req = rtu(2, 3, bytes.fromhex("0bba0002"))
    good = rtu(2, 3, 4, bytes.fromhex("406d0000"))
    bad = good[:-1] + bytes([good[-1] ^ 0xFF])
    with expected_protocol([(req, bad), (req, good)]) as t:
        bus = ModbusClient(t, "rtu", unit=2, timeout_s=0.05, retries=1)
        assert bus.read_holding(3002, 2) == [0x406D, 0]
    assert bus.stats.protocol_errors == 1 and bus.stats.retries == 1
    with expected_protocol([(req, bad), (req, bad)]) as t:
        with pytest.raises(ProtocolError, match="CRC error.*after 2 attempts"):
            ModbusClient(t, "rtu", unit=2, timeout_s=0.05, retries=1).read_holding(3002, 2)


def test_silent_device_times_out_within_bound():
    import time

    req = rtu(2, 3, bytes.fromhex("0bba0002"))
    with expected_protocol([(req, None), (req, None)]) as t:
        bus = ModbusClient(t, "rtu", unit=2, timeout_s=0.05, retries=1)
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout, match="no reply"):
            bus.read_holding(3002, 2)
        assert time.monotonic() - t0 < 0.5
    assert bus.stats.timeouts == 2


@pytest.mark.parametrize("reply,match", [
    (rtu(5, 3, 4, bytes(4)), "from unit 5"),
    (rtu(2, 4, 4, bytes(4)), "function code 0x04, expected 0x03"),
    (bytes.fromhex("020304406d"), "truncated"),
])
def test_malformed_replies_are_protocol_errors(reply, match):
    req = rtu(2, 3, bytes.fromhex("0bba0002"))
    with expected_protocol([(req, reply)]) as t:
        with pytest.raises(ProtocolError, match=match):
            ModbusClient(t, "rtu", unit=2, timeout_s=0.05, retries=0).read_holding(3002, 2)


def test_disconnect_without_reconnect_raises():
    class Dead(ExpectedProtocolTransport):
        def write(self, data):
            self.close()
            raise DeviceDisconnected("gone")

    t = Dead([])
    t.open()
    with pytest.raises(DeviceDisconnected, match="gone"):
        ModbusClient(t, "rtu", reconnect=False, retries=2).read_holding(0, 1)


def test_argument_checks_before_sending():
    with expected_protocol([]) as t:
        bus = ModbusClient(t, "rtu")
        with pytest.raises(ValueError, match="count must be 1..125"):
            bus.read_holding(0, 126)
        with pytest.raises(ValueError, match="0..65535"):
            bus.write_registers(0, [70000])


VALUES = {"float32": 3.25, "int32": -123456, "uint32": 0xDEADBEEF, "float64": -1.5e-3, "uint16": 0xBEEF}
EXPECTED = {  # float32 3.25 = 40 50 00 00
    WordOrder.ABCD: [0x4050, 0x0000], WordOrder.CDAB: [0x0000, 0x4050],
    WordOrder.BADC: [0x5040, 0x0000], WordOrder.DCBA: [0x0000, 0x5040],
}


@pytest.mark.parametrize("order", list(WordOrder))
def test_word_orders(order):
    assert encode_value(3.25, "float32", order) == EXPECTED[order]
    assert encode_value(0x11223344, "uint32", order) == {
        "ABCD": [0x1122, 0x3344], "CDAB": [0x3344, 0x1122], "BADC": [0x2211, 0x4433], "DCBA": [0x4433, 0x2211]}[order.value]
    for dtype, v in VALUES.items():
        assert decode_registers(encode_value(v, dtype, order), dtype, order) == pytest.approx(v)


def test_flowmeter_cdab_word_order_exact_bytes():
    req = rtu(2, 3, bytes.fromhex("0bba0002"))
    alarm_req = rtu(2, 3, bytes.fromhex("0c1c0001"))
    flow = rtu(2, 3, 4, bytes.fromhex("0000406d"))  # 3.703125 low word first
    with expected_protocol([(req, flow), (alarm_req, rtu(2, 3, 2, bytes.fromhex("0000")))]) as t:
        fm = Flowmeter(ModbusClient(t, "rtu", unit=2, timeout_s=0.05), word_order="CDAB")
        r = fm.read_flow()
    assert r.value == pytest.approx(3.703125) and r.units == "m3/s" and r.quality.name == "OVER_RANGE"


def test_valve_manoeuvre_is_one_write_and_ranges_checked_before_sending():
    body = encode_value(32.0, "float32") + encode_value(-5.5, "float32") + encode_value(0.0, "float32")
    req = rtu(3, 0x10, bytes.fromhex("000a0006"), 12, b"".join(struct.pack(">H", w) for w in body))
    with expected_protocol([(req, rtu(3, 0x10, bytes.fromhex("000a0006")))]) as t:
        v = ValveActuator(ModbusClient(t, "rtu", unit=3, timeout_s=0.05))
        v.set_manoeuvre(32.0, -5.5, 0.0)
        with pytest.raises(RangeError, match="beta.*above the profile maximum"):
            v.set_manoeuvre(500.0, -5.5)
        with pytest.raises(RangeError, match="end_position"):
            v.set_manoeuvre(32.0, -5.5, 120.0)


# ---------------------------------------------------------------- every reply check, byte-exact

def mbap(tid: int, unit: int, pdu: bytes, length: int | None = None) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1 if length is None else length, unit) + pdu


READ_3002 = rtu(2, 3, bytes.fromhex("0bba0002"))  # read holding 3002+2 from unit 2
GOOD_3002 = rtu(2, 3, 4, bytes.fromhex("406d0000"))


def rtu_bus(t, **kw):
    kw.setdefault("timeout_s", 0.05)
    kw.setdefault("retries", 0)
    return ModbusClient(t, "rtu", unit=2, name="flowmeter", **kw)


@pytest.mark.parametrize("reply,cls,reason,match", [
    (GOOD_3002[:-3], FrameError, "short_frame", "truncated reply: 6 of 9 bytes"),
    (rtu(2, 3, 2, bytes.fromhex("406d")), FrameError, "byte_count", "byte count 2, expected 4"),  # valid CRC, 1 register
    (rtu(2, 3, 6, bytes(6)), FrameError, "byte_count", "byte count 6, expected 4"),
    (GOOD_3002 + b"\x00", FrameError, "long_frame", "bytes trailing the reply frame"),
    (GOOD_3002[:-1] + bytes([GOOD_3002[-1] ^ 1]), ChecksumError, "bad_crc", "CRC error"),
    (rtu(7, 3, 4, bytes.fromhex("406d0000")), ReplyMismatch, "wrong_unit", "reply from unit 7"),
    (rtu(2, 4, 4, bytes(4)), ReplyMismatch, "wrong_function", "function code 0x04, expected 0x03"),
    (rtu(2, 0x84, 2), ReplyMismatch, "wrong_function", "function code 0x84"),  # another function's exception
])
def test_rtu_reply_checks(reply, cls, reason, match):
    with expected_protocol([(READ_3002, reply)]) as t:
        with pytest.raises(cls, match=match) as ei:
            rtu_bus(t).read_holding(3002, 2)
    e = ei.value
    assert isinstance(e, ProtocolError) and e.reason == reason and e.device == "flowmeter"
    assert "flowmeter unit 2: read holding 3002+2" in str(e)


def test_rtu_rejected_reply_is_retried_after_the_line_goes_quiet():
    bad = GOOD_3002 + b"\xff\xff"  # a frame glued to junk: never used
    with expected_protocol([(READ_3002, bad), (READ_3002, GOOD_3002)]) as t:
        bus = rtu_bus(t, retries=1)
        assert bus.read_holding(3002, 2) == [0x406D, 0]
    assert bus.stats.protocol_errors == 1 and bus.stats.retries == 1


def test_rtu_write_echo_must_match_the_request():
    req = rtu(3, 0x10, bytes.fromhex("00000001"), 2, bytes.fromhex("0001"))
    echo = rtu(3, 0x10, bytes.fromhex("00010001"))  # acknowledges address 1, not 0
    with expected_protocol([(req, echo)]) as t:
        with pytest.raises(ReplyMismatch, match="write acknowledged as 1\\+1") as ei:
            ModbusClient(t, "rtu", unit=3, timeout_s=0.05, retries=0).write_registers(0, [1])
    assert ei.value.reason == "wrong_echo"


def test_rtu_late_reply_is_dropped_not_taken_for_the_next_request():
    """Request 1 times out; its reply arrives late; request 2 (same shape, other address) gets its own."""
    read_3100 = rtu(2, 3, bytes.fromhex("0c1c0002"))
    good_3100 = rtu(2, 3, 4, bytes.fromhex("00010002"))
    with expected_protocol([(READ_3002, Late(GOOD_3002)), (read_3100, good_3100)]) as t:
        bus = rtu_bus(t)
        with pytest.raises(DeviceTimeout, match="no reply to read holding 3002\\+2"):
            bus.read_holding(3002, 2)
        assert bus.read_holding(3100, 2) == [1, 2]  # not 0x406d, 0
    assert bytes(t.discarded) == GOOD_3002 or bus.stats.flushed_bytes == len(GOOD_3002)


def test_rtu_late_reply_glued_before_the_next_reply_is_rejected_then_retried():
    """The worst case: the late frame arrives just before the next reply, with the same shape.
    The frame is followed by bytes within the inter-frame silence: rejected (long_frame), the
    line is let go quiet, the request is sent again and its own reply is used."""
    read_3100 = rtu(2, 3, bytes.fromhex("0c1c0002"))
    good_3100 = rtu(2, 3, 4, bytes.fromhex("00010002"))
    pairs = [(READ_3002, Late(GOOD_3002, with_next=True)), (read_3100, good_3100), (read_3100, good_3100)]
    with expected_protocol(pairs) as t:
        bus = rtu_bus(t)
        with pytest.raises(DeviceTimeout):
            bus.read_holding(3002, 2)
        bus.retries = 1
        assert bus.read_holding(3100, 2) == [1, 2]
    assert bus.stats.protocol_errors == 1 and bus.stats.retries == 1


def test_rtu_backlog_in_pieces_is_drained_before_the_retry():
    """A rejected frame, then 30 ms later a stale reply of the same shape (a slave answering what it queued
    while busy, in pieces further apart than t3.5), and the retry's own reply 40 ms after the retry. The line
    is quiet only after QUIET_AFTER_BYTES_S without a byte: the stale frame is dropped, not taken as the
    retry's answer (a loaded pair read the product code after the flow this way)."""
    stale = rtu(2, 3, 4, bytes.fromhex("11110000"))
    pairs = [(READ_3002, Trickle(((0.0, GOOD_3002 + b"\xff"), (0.03, stale)))),
             (READ_3002, Trickle(((0.04, GOOD_3002),)))]
    with expected_protocol(pairs) as t:
        bus = rtu_bus(t, retries=1, timeout_s=0.5)
        assert bus.read_holding(3002, 2) == [0x406D, 0]
    assert bus.stats.protocol_errors == 1 and bus.stats.flushed_bytes >= len(stale)


def test_rtu_exception_reply_is_checked_too():
    with expected_protocol([(READ_3002, rtu(2, 0x83, 2)[:-1] + b"\x00")]) as t:
        with pytest.raises(ChecksumError):
            rtu_bus(t).read_holding(3002, 2)


TCP_REQ = mbap(1, 3, bytes.fromhex("0300140005"))  # read holding 20+5 from unit 3


def tcp_bus(t, **kw):
    kw.setdefault("timeout_s", 0.05)
    kw.setdefault("retries", 0)
    return ModbusClient(t, "tcp", unit=3, name="valve", **kw)


@pytest.mark.parametrize("reply,cls,reason,match", [
    (mbap(1, 3, bytes([3, 10]) + bytes(10))[:-4], FrameError, "short_frame", "truncated reply"),
    (mbap(1, 3, bytes([3, 8]) + bytes(8)), FrameError, "byte_count", "byte count 8, expected 10"),
    (mbap(1, 3, bytes([3, 10]) + bytes(12)), FrameError, "long_frame", "PDU of 14 bytes, expected 12"),
    (mbap(1, 3, bytes([3, 10]) + bytes(10), length=300), FrameError, "bad_header", "length 300"),
    (struct.pack(">HHHB", 1, 7, 13, 3) + bytes([3, 10]) + bytes(10), FrameError, "bad_header", "protocol 7"),
    (mbap(9, 3, bytes([3, 10]) + bytes(10)), ReplyMismatch, "wrong_transaction", "transaction id 9, expected 1"),
    (mbap(1, 4, bytes([3, 10]) + bytes(10)), ReplyMismatch, "wrong_unit", "reply from unit 4"),
    (mbap(1, 3, bytes([4, 10]) + bytes(10)), ReplyMismatch, "wrong_function", "function code 0x04"),
    (mbap(1, 3, bytes([0x83, 2, 0])), FrameError, "long_frame", "exception reply of wrong length"),
])
def test_tcp_reply_checks(reply, cls, reason, match):
    with expected_protocol([(TCP_REQ, reply)]) as t:
        with pytest.raises(cls, match=match) as ei:
            tcp_bus(t).read_holding(20, 5)
    assert ei.value.reason == reason and ei.value.device == "valve"


def test_tcp_exception_reply_names_device_and_code():
    with expected_protocol([(TCP_REQ, mbap(1, 3, bytes([0x83, 2])))]) as t:
        with pytest.raises(DeviceException, match="valve unit 3: read holding 20\\+5 refused \\(exception 2: ") as ei:
            tcp_bus(t, retries=3).read_holding(20, 5)
    assert ei.value.code == 2 and ei.value.reason == "exception" and ei.value.device == "valve"


def test_tcp_garbled_reply_then_good_retry():
    good = mbap(2, 3, bytes([3, 10]) + bytes(range(10)))
    garbled = bytes(b ^ 0x5A for b in mbap(1, 3, bytes([3, 10]) + bytes(10)))
    req2 = mbap(2, 3, bytes.fromhex("0300140005"))
    with expected_protocol([(TCP_REQ, garbled), (req2, good)]) as t:
        bus = tcp_bus(t, retries=1)
        assert bus.read_holding(20, 5) == [0x0001, 0x0203, 0x0405, 0x0607, 0x0809]
    assert bus.stats.protocol_errors == 1


def test_retries_exhausted_keep_the_named_error():
    with expected_protocol([(READ_3002, GOOD_3002[:-1]), (READ_3002, GOOD_3002[:-1])]) as t:
        with pytest.raises(FrameError, match="after 2 attempts") as ei:
            rtu_bus(t, retries=1).read_holding(3002, 2)
    assert ei.value.reason == "short_frame" and ei.value.device == "flowmeter"


# ---------------------------------------------------------------- several sections (a transducer on ch2)

def test_a_buffered_pressure_source_of_two_sections_records_inputs_0_to_2_exact_bytes():
    """The pressure source asked for the valve's transducer (ch0) and the one on ch2: the module is stopped,
    then told its rate and 3 buffered channels (ch0..ch2: the position on ch1 comes along), all FC16; the
    look before arming is one polled read of every input and its status."""
    from velab.drivers.modbus_adc import ModbusADC
    from velab.drivers.pressure_source import BufferedSource

    def write(address, words):
        head = struct.pack(">HH", address, len(words))
        return (rtu(1, 0x10, head, 2 * len(words), b"".join(struct.pack(">H", w) for w in words)),
                rtu(1, 0x10, head))

    ai = [0x8000, 0xA000, 0x8800, 0x2AAA]  # raw over 0..24 mA: 12, 15, 12.75, 4 mA
    pairs = [
        write(1007, [0]),  # acquisition_control: stop
        write(1002, [0, 2000]),  # sample_rate (uint32, ABCD)
        write(1004, [3]),  # buffer_channels: ch0..ch2
        (rtu(1, 3, struct.pack(">HH", 0, 4)), rtu(1, 3, 8, b"".join(struct.pack(">H", w) for w in ai))),
        (rtu(1, 3, struct.pack(">HH", 100, 8)), rtu(1, 3, 16, bytes(16))),
    ]
    with expected_protocol(pairs) as t:
        adc = ModbusADC(ModbusClient(t, "rtu", unit=1, timeout_s=0.05, retries=0), "modbus_adc_sections")
        src = BufferedSource(adc, "pressure_adc")
        assert src.pressure_channels() == ("pressure", "pressure_2", "pressure_3")
        src.configure(2000, ("pressure", "pressure_2"))
        looks = src.spot_heads(2000, ("pressure", "pressure_2"))
    from velab.drivers.base import pressure_to_head_m

    for ch, raw in (("pressure", ai[0]), ("pressure_2", ai[2])):
        mA = raw * 24.0 / 65535
        assert looks[ch][0] == pytest.approx(pressure_to_head_m((mA - 4) / 16 * 6e5), rel=1e-12)
        assert looks[ch][1] == "ok"
