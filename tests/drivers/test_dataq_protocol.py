"""Byte-exact protocol tests for the DATAQ DI-series driver, written from the vendor's "Data Acquisition
Instrument Command Protocol" (2019; pages cited): the bytes the driver must write, the bytes the device
answers (PyMeasure's expected_protocol idea), the binary stream decoded, the overflow report, profiles."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from velab.drivers import dataq_protocol as dq
from velab.drivers.base import (DeviceException, DeviceFault, DeviceTimeout, ProfileError, Quality, ReplyMismatch,
                                StreamSilent)
from velab.drivers.bench import BenchDevice
from velab.drivers.dataq import DataqDAQ
from velab.drivers.dataq_bench import open_dataq
from velab.drivers.dataq_profile import DataqProfileError, default_profile, load_profile
from velab.errors import ConfigError

pytestmark = pytest.mark.timeout(30)

IDENTIFY_2108 = [(b"stop\r", b"stop\r"), (b"info 0\r", b"info 0 DATAQ\r"), (b"info 1\r", b"info 1 2108\r"),
                 (b"info 2\r", b"info 2 79\r"), (b"info 6\r", b"info 6 5A1B2C3D\r")]


class ExpectedProtocol:
    """A serial-like fake: each write must be the next expected command; its reply then becomes readable."""

    def __init__(self, pairs, timeout: float = 0.01):
        self.pairs = list(pairs)
        self.timeout = timeout
        self.rx = bytearray()
        self.lock = threading.Lock()
        self.is_open = True
        self.mismatch: str | None = None

    def write(self, data: bytes) -> int:
        if not self.pairs:
            self.mismatch = f"unexpected write {bytes(data)!r}"
            raise AssertionError(self.mismatch)
        sent, reply = self.pairs.pop(0)
        if bytes(data) != sent:
            self.mismatch = f"wrote {bytes(data)!r}, expected {sent!r}"
            raise AssertionError(self.mismatch)
        self.feed(reply)
        return len(data)

    def feed(self, data: bytes) -> None:
        with self.lock:
            self.rx += data

    @property
    def in_waiting(self) -> int:
        return len(self.rx)

    def read(self, size: int = 1) -> bytes:
        with self.lock:
            if self.rx:
                out = bytes(self.rx[:size])
                del self.rx[:size]
                return out
        time.sleep(self.timeout)
        return b""

    def open(self) -> None:
        self.is_open = True

    def close(self) -> None:
        self.is_open = False

    def done(self) -> None:
        assert self.mismatch is None, self.mismatch
        assert not self.pairs, f"not written: {self.pairs[0][0]!r} and {len(self.pairs) - 1} more"


def stream_2108(counts, din=0) -> bytes:
    """DI-2108 scans (analog 0, analog 1, digital word) as the document lays them out [p.67]."""
    c = np.asarray(counts, dtype=np.int32)
    words = np.column_stack([c & 0xFFFF, np.full(len(c), int(dq.digital_word(din)))])
    return words.astype("<u2").tobytes()


def profile(**kw):
    kw.setdefault("data_timeout_s", 0.5)
    kw.setdefault("command_timeout_s", 0.3)
    kw.setdefault("reconnect", False)
    return default_profile(**kw)


# ---------------------------------------------------------------- command bytes


def test_commands_are_ascii_words_ended_by_cr():
    # p.16: command and arguments separated by a space, decimal, terminated by a carriage return
    assert dq.info(1) == b"info 1\r"
    assert dq.stop() == b"stop\r"
    assert dq.start() == b"start 0\r"  # p.49: start 0
    assert dq.encode(0) == b"encode 0\r"
    assert dq.ps(3) == b"ps 3\r"
    assert dq.slist(5, 10) == b"slist 5 10\r"  # p.39's example
    assert dq.srate(11718) == b"srate 11718\r"
    assert dq.dec(512) == b"dec 512\r" and dq.deca(3) == b"deca 3\r"
    assert dq.endo(20) == b"endo 20\r" and dq.dout(4) == b"dout 4\r" and dq.din() == b"din\r"  # p.57-58
    with pytest.raises(ValueError):
        dq.dout(128)
    with pytest.raises(ValueError):
        dq.ps(8)


def test_reply_is_the_echo_then_the_response():
    assert dq.reply_text(dq.info(1), b"info 1 2008\r") == "2008"  # p.21's example
    assert dq.reply_text(dq.ps(1), b"ps 1\r") == ""
    assert dq.reply_text(dq.din(), b"din 20\r") == "20"  # p.58: D2 and D4 set
    with pytest.raises(dq.ReplyError):
        dq.reply_text(dq.info(1), b"info 2 65\r")
    assert dq.firmware_text("65") == "1.01"  # p.20: 65 hex = 101 = firmware 1.01


def test_model_table_from_the_srate_table():
    # p.48: dividend 60 MHz; srate 375..65535 (DI-1100: 1500/2000/2500/3000 by channel count); dec 1..512 (DI-2108)
    d2108, d1100 = dq.model("DI-2108"), dq.model("1100")
    assert d2108.rate_bounds(2) == pytest.approx((60e6 / (65535 * 512), 160_000.0))
    assert d1100.rate_bounds(1)[1] == pytest.approx(40_000.0)
    assert d1100.rate_bounds(4) == pytest.approx((60e6 / 65535, 20_000.0))
    assert not d1100.digital_io and d2108.digital_io and dq.model("DI-1110").digital_io  # p.57
    plan = dq.rate_plan(d2108, 10.0, 2)  # the vendor example's 10 Hz needs dec (there: 11718 x 512)
    assert plan.dec > 1 and plan.srate <= 65535 and plan.rate_hz == pytest.approx(10.0, rel=1e-4)
    assert dq.rate_plan(d2108, 1000.0, 2) == dq.RatePlan(60000, 1, 1, 1000.0)
    with pytest.raises(ValueError, match="915.5"):
        dq.rate_plan(d1100, 500.0, 2)  # no dec on the DI-1100: nothing slower than 60 MHz / 65535
    with pytest.raises(ValueError):
        dq.model("DI-9999")


def test_counts_to_volts_per_the_coding_tables():
    # p.68: 16-bit, volts = 10 x counts / 32768; p.61: DI-1100 12-bit, volts = 10 x counts / 2048
    d2108, d1100 = dq.model("DI-2108"), dq.model("DI-1100")
    assert d2108.volts(32767) == pytest.approx(9.9997, abs=1e-4) and d2108.volts(-32768) == -10.0
    assert d2108.volts(1) == pytest.approx(0.0003, abs=1e-4)
    assert d1100.volts(2047) == pytest.approx(9.995, abs=1e-3) and d1100.volts(-2048) == -10.0
    assert d1100.volts(-1) == pytest.approx(-0.0048, abs=1e-4)


def test_di1100_stream_word_carries_d1_d0_in_position_0():
    # p.61: position 0 byte 1 = A3 A2 A1 A0 0 0 D1 D0, byte 2 = A11..A4; other positions 0 0 0 0 in the low nibble
    spec = dq.model("DI-1100")
    words = dq.encode_words(spec, np.array([[-1, 2047]]), np.array([2]))
    assert words.astype("<u2").tobytes() == bytes([0xF2, 0xFF, 0xF0, 0x7F])
    lay = dq.scan_layout(spec, [0, 1])
    counts, dig, ok = lay.decode(words.astype("<u2").tobytes())
    assert counts.tolist() == [[-1, 2047]] and dig.tolist() == [2] and ok.all()
    _, _, ok = lay.decode(bytes([0xF2, 0xFF, 0xF1, 0x7F]))  # a set spare bit: out of frame
    assert not ok.any()


def test_digital_word_layout():
    # p.67: byte 17 = 0 0 0 0 0 0 ~D1 ~D0, byte 18 = 0 D6..D0
    assert int(dq.digital_word(0b0000101)).to_bytes(2, "little") == bytes([0b10, 0b0000101])
    assert dq.digital_word_valid(dq.digital_word(np.arange(128))).all()
    assert not dq.digital_word_valid(np.array([0x0000, 0x0103, 0x8003]) ).any()


# ---------------------------------------------------------------- exchanges


def test_identify_byte_exact():
    t = ExpectedProtocol(IDENTIFY_2108)
    daq = DataqDAQ(t, profile())
    assert daq.identify() == {"manufacturer": "DATAQ", "model": "DI-2108", "serial": "5A1B2C3D", "firmware": "1.21"}
    t.done()


def test_configure_byte_exact_di2108():
    # stop, identity, then p.38 encode, p.20 ps, p.39 slist (the digital word last: a framing check), p.48 srate,
    # p.52 dec, p.57 endo (D0 a switch), p.58 dout
    t = ExpectedProtocol(IDENTIFY_2108 + [
        (b"encode 0\r", b"encode 0\r"), (b"ps 1\r", b"ps 1\r"), (b"slist 0 0\r", b"slist 0 0\r"),
        (b"slist 1 1\r", b"slist 1 1\r"), (b"slist 2 8\r", b"slist 2 8\r"), (b"srate 60000\r", b"srate 60000\r"),
        (b"dec 1\r", b"dec 1\r"), (b"endo 1\r", b"endo 1\r"), (b"dout 0\r", b"dout 0\r")])
    daq = DataqDAQ(t, profile())
    assert daq.configure(1000.0) == 1000.0
    t.done()


def test_configure_byte_exact_di1100_has_no_dec_nor_digital_commands():
    ident = [(b"stop\r", b"stop\r"), (b"info 0\r", b"info 0 DATAQ\r"), (b"info 1\r", b"info 1 1100\r"),
             (b"info 2\r", b"info 2 65\r"), (b"info 6\r", b"info 6 00112233\r")]
    t = ExpectedProtocol(ident + [(b"encode 0\r", b"encode 0\r"), (b"ps 1\r", b"ps 1\r"),
                                  (b"slist 0 0\r", b"slist 0 0\r"), (b"slist 1 1\r", b"slist 1 1\r"),
                                  (b"srate 40000\r", b"srate 40000\r")])
    daq = DataqDAQ(t, profile(model="DI-1100", digital_outputs=()))
    assert daq.configure(1500.0) == 1500.0
    t.done()
    with pytest.raises(DeviceException, match="no digital outputs"):
        daq.write_digital(0, True)


def test_read_analog_after_the_reader_failed_raises_its_error():
    """Started, the reader ended on StreamSilent, not stopped: a position read (the fired valve's DaqPosition) is
    that error, named; nothing is sent (no short scan of one channel in the middle of a run)."""
    t = ExpectedProtocol([])
    daq = DataqDAQ(t, profile())
    daq._thread = threading.Thread(target=lambda: None)  # (never started: not alive)
    daq.error = StreamSilent("DATAQ DAQ: no in-frame scan for 1 s", device="DATAQ DAQ")
    with pytest.raises(StreamSilent, match="valve_position: no reading: the scan .* ended: .*no in-frame scan"):
        daq.read_analog("valve_position")
    daq._thread = None
    t.done()


def test_wrong_model_is_a_profile_error():
    t = ExpectedProtocol(IDENTIFY_2108[:2] + [(b"info 1\r", b"info 1 1100\r")] + IDENTIFY_2108[3:])
    with pytest.raises(ProfileError, match="for a DI-2108, the device says it is a DI-1100"):
        DataqDAQ(t, profile()).configure(1000.0)


def test_reply_not_the_echo_is_named():
    t = ExpectedProtocol([(b"stop\r", b"stop\r"), (b"info 0\r", b"info 9 DATAQ\r")])
    with pytest.raises(ReplyMismatch, match="not its echo"):
        DataqDAQ(t, profile()).identify()


def test_no_echo_is_a_timeout():
    t = ExpectedProtocol([(b"stop\r", b"stop\r"), (b"info 0\r", b"")])
    with pytest.raises(DeviceTimeout, match="no echo of 'info 0'"):
        DataqDAQ(t, profile()).identify()


def test_stop_skips_a_stream_left_running():
    # the device may still be scanning from an earlier session: everything up to the echo is skipped
    t = ExpectedProtocol([(b"stop\r", stream_2108(np.zeros((50, 2))) + b"stop\r")] + IDENTIFY_2108[1:])
    assert DataqDAQ(t, profile()).identify()["model"] == "DI-2108"
    t.done()


def _configured(extra=(), **kw):
    t = ExpectedProtocol(IDENTIFY_2108 + [
        (b"encode 0\r", b"encode 0\r"), (b"ps 1\r", b"ps 1\r"), (b"slist 0 0\r", b"slist 0 0\r"),
        (b"slist 1 1\r", b"slist 1 1\r"), (b"slist 2 8\r", b"slist 2 8\r"), (b"srate 60000\r", b"srate 60000\r"),
        (b"dec 1\r", b"dec 1\r"), (b"endo 1\r", b"endo 1\r"), (b"dout 0\r", b"dout 0\r")] + list(extra))
    daq = DataqDAQ(t, profile(**kw))
    daq.configure(1000.0)
    return t, daq


def collect(daq, n, timeout=5.0):
    blocks, deadline = [], time.monotonic() + timeout
    while sum(b.n for b in blocks) < n and time.monotonic() < deadline:
        blocks.append(daq.get_block(timeout=2.0))
    return blocks


def test_stream_decodes_to_engineering_values():
    # 4-20 mA through 250 ohm: 8 mA = 2 V = 6553.6 counts -> 1.5 bar; the position 3 V = 50 %
    counts = np.tile([[6554, 9830]], (300, 1))
    t, daq = _configured([(b"start 0\r", stream_2108(counts, din=0b1)), (b"stop\r", b"stop\r")])
    daq.start()
    blocks = collect(daq, 290)
    b = blocks[0]
    assert b.channels == ("pressure", "valve_position") and b.units == ("Pa", "%") and b.rate_hz == 1000.0
    assert b.raw[0].tolist() == [6554, 9830]
    assert b.signal[0, 0] == pytest.approx(8.0, abs=1e-3) and b.signal[0, 1] == pytest.approx(3.0, abs=1e-3)
    assert b.values[0, 0] == pytest.approx(1.5e5, rel=1e-3) and b.values[0, 1] == pytest.approx(50.0, abs=0.01)
    assert b.quality == (Quality.OK, Quality.OK) and b.lost_before == 0
    assert daq.latest("pressure").value == pytest.approx(1.5e5, rel=1e-3)
    assert daq.read_digital() == 1  # while scanning: the stream's digital word
    daq.stop()
    t.done()
    assert daq.latest("pressure") is None


def test_dout_while_scanning_is_sent_without_waiting_for_an_echo():
    # p.16: commands do not echo while scanning
    t, daq = _configured([(b"start 0\r", stream_2108(np.zeros((20, 2)))), (b"dout 1\r", b""),
                          (b"stop\r", b"stop\r")])
    daq.start()
    daq.write_digital(0, True)
    with pytest.raises(DeviceException, match="not a digital output"):
        daq.write_digital(3, True)
    daq.stop()
    t.done()


def test_loop_quality_open_loop_fault_over_range():
    # 0 V: open loop (< 3.6 mA); 5.5 V = 22 mA: NE43 sensor fault; 5.1 V = 20.4 mA: over range (beyond 20 + 2 %)
    v = np.array([0.0, 5.5, 5.1, 3.0])
    counts = np.column_stack([np.rint(v / 10 * 32768), np.full(4, 9830)]).repeat(30, axis=0)
    t, daq = _configured([(b"start 0\r", stream_2108(counts)), (b"stop\r", b"stop\r")])
    daq.start()
    blocks = collect(daq, 100)
    daq.stop()
    sq = np.concatenate([b.sample_quality[:, 0] for b in blocks])
    from velab.drivers.blocks import QUALITY_CODES
    got = [QUALITY_CODES[int(c)] for c in sq[::30]]
    assert got[:4] == [Quality.OPEN_LOOP, Quality.SENSOR_FAULT, Quality.OVER_RANGE, Quality.OK]


def test_overflow_report_is_a_named_fault():
    # p.50: the instrument stops scanning and places "stop 01" in the last seven bytes of its final response
    t, daq = _configured([(b"start 0\r", stream_2108(np.zeros((40, 2))) + dq.OVERFLOW_REPORT)])
    daq.start()
    with pytest.raises(DeviceFault, match="stop 01"):
        collect(daq, 10**6)
    assert isinstance(daq.error, DeviceFault)


def test_dropped_byte_is_skipped_and_counted():
    counts = np.column_stack([np.arange(400) * 7 - 1400, np.full(400, 9830)])
    data = bytearray(stream_2108(counts))
    del data[6 * 150 + 3]  # one byte of scan 150 lost on the way
    t, daq = _configured([(b"start 0\r", bytes(data)), (b"stop\r", b"stop\r")])
    daq.start()
    blocks = collect(daq, 380)
    daq.stop()
    got = np.concatenate([b.raw[:, 0] for b in blocks])
    assert set(got.tolist()) <= set(counts[:, 0].tolist())  # nothing out of frame delivered
    assert sum(b.lost_before for b in blocks) + got.size >= 390  # the skipped scans are counted
    i = next(k for k, b in enumerate(blocks) if b.lost_before)
    assert blocks[i].first_index == blocks[i - 1].next_index + blocks[i].lost_before  # the time axis keeps going
    assert daq.stats.resyncs == 1


def test_silence_is_stream_silent():
    t, daq = _configured([(b"start 0\r", stream_2108(np.zeros((10, 2))))], data_timeout_s=0.3)
    daq.start()
    with pytest.raises(StreamSilent):
        collect(daq, 10**6)


# ---------------------------------------------------------------- profiles and bench


def test_shipped_profiles_load():
    assert load_profile("dataq_di2108").digital_outputs == (0,)
    assert load_profile("dataq_di1110").model == "DI-1110"
    p = load_profile("dataq_di1100")
    assert p.model == "DI-1100" and not p.digital_outputs and p.channel("pressure").shunt_ohm == 250.0


@pytest.mark.parametrize("edit, match", [
    ('s/input = 1$/input = 9/', r"channels.valve_position.input: must be 0..7"),
    ('s/^outputs = \\[0\\].*/outputs = [0]\\nfoo = 1/', r"digital.foo: unknown key"),
    ('s/rate_hz = 2000 .*/rate_hz = 1e6/', r"acquisition.rate_hz: must be"),
    ('s/shunt_ohm = 250.0 .*/shunt_ohm = 1000.0/', r"channels.pressure.signal_hi: outside the \+-10 V input range"),
    ('s/model = "DI-2108"/model = "DI-2008"/', r"device.model: .*unsupported model"),
])
def test_profile_errors_name_file_and_key(tmp_path, edit, match):
    import re
    import subprocess

    from velab.configpath import find_config
    src = find_config("devices", "dataq_di2108")
    dst = tmp_path / "bad.toml"
    dst.write_text(subprocess.run(["sed", "-e", edit, str(src)], capture_output=True, text=True, check=True).stdout)
    with pytest.raises(DataqProfileError) as ei:
        load_profile(dst)
    msg = str(ei.value)
    assert "\n" not in msg and "bad.toml" in msg and re.search(match, msg), msg
    assert isinstance(ei.value, ConfigError)


def test_di1100_profile_refuses_digital_outputs(tmp_path):
    from velab.configpath import find_config
    text = find_config("devices", "dataq_di1100").read_text().replace("outputs = []", "outputs = [0]")
    (tmp_path / "p.toml").write_text(text)
    with pytest.raises(DataqProfileError, match="digital.outputs: the DI-1100 has no digital outputs"):
        load_profile(tmp_path / "p.toml")


def test_bench_keys_are_checked():
    with pytest.raises(ProfileError, match=r"\[devices.daq\]: unknown key 'baud'"):
        open_dataq(BenchDevice("daq", "dataq", None, {"url": "socket://127.0.0.1:1", "baud": 9600}), connect=False)
    with pytest.raises(ProfileError, match="rate_hz: 'fast' is not a number"):
        open_dataq(BenchDevice("daq", "dataq", None, {"url": "x", "rate_hz": "fast"}), connect=False)
    with pytest.raises(ProfileError, match="rate_hz: 1e.07 is outside"):
        open_dataq(BenchDevice("daq", "dataq", None, {"url": "x", "rate_hz": 1e7}), connect=False)
    daq = open_dataq(BenchDevice("daq", "dataq", "dataq_di1100", {"url": "socket://127.0.0.1:1", "data_s": 2}),
                     connect=False)
    assert daq.spec.name == "DI-1100" and daq.profile.data_timeout_s == 2.0
