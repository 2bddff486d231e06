"""Byte-exact protocol tests for the streaming ADC driver (no I/O, PyMeasure
expected_protocol style): the bytes the driver writes, the replies it gets,
frames in -> samples out, CRC, error replies, corrupted streams, profile errors."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from velab.drivers.base import DeviceException, DeviceTimeout, ProtocolError, Quality
from velab.drivers.blocks import QUALITY_CODE
from velab.drivers.streaming_adc import (
    FLAG_OVERRUN,
    FrameParser,
    StreamingADC,
    StreamingADCProfileError,
    actual_rate,
    crc16,
    default_profile,
    encode_frame,
    load_profile,
    pressure_to_head_m,
)
from velab.errors import ConfigError

pytestmark = pytest.mark.timeout(30)


class ExpectedProtocol:
    """A serial-like fake: every write must equal the next expected command;
    its reply (and any stream bytes given with it) then becomes readable."""

    def __init__(self, pairs, timeout: float = 0.01):
        self.pairs = list(pairs)
        self.timeout = timeout
        self.rx = bytearray()
        self.lock = threading.Lock()
        self.is_open = True
        self.written: list[bytes] = []
        self.mismatch: str | None = None

    def write(self, data: bytes) -> int:
        self.written.append(bytes(data))
        if not self.pairs:
            self.mismatch = f"unexpected write {data!r}"
            raise AssertionError(self.mismatch)
        sent, reply = self.pairs.pop(0)
        if bytes(data) != sent:
            self.mismatch = f"wrote {data!r}, expected {sent!r}"
            raise AssertionError(self.mismatch)
        with self.lock:
            self.rx += reply
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

    def assert_done(self) -> None:
        assert self.mismatch is None, self.mismatch
        assert not self.pairs, f"not sent: {self.pairs}"


CONFIG_2CH = [
    (b"STOP\n", b"OK STOP 0\n"),
    (b"RATE 10000\n", b"OK RATE 10000\n"),
    (b"CHAN 0,1\n", b"OK CHAN 0,1\n"),
    (b"RANGE 0 25MA\n", b"OK RANGE 0 25MA\n"),
    (b"RANGE 1 25MA\n", b"OK RANGE 1 25MA\n"),
    (b"BLOCK 4\n", b"OK BLOCK 4\n"),
]


def profile(**kw):
    kw.setdefault("command_timeout_s", 0.3)
    kw.setdefault("data_timeout_s", 0.5)
    kw.setdefault("reconnect", False)
    kw.setdefault("poll_s", 0.01)
    return default_profile(**kw)


def frame(seq, first, raw, mask=0b11, flags=0):
    return encode_frame(seq, first, mask, np.asarray(raw, dtype=np.int16), flags)


def counts(first, k=4, nch=2):
    """Distinct, checkable counts: sample i of channel c = 1000*c + i."""
    i = np.arange(first, first + k)
    return np.stack([1000 * c + i for c in range(nch)], axis=1)


def configured(extra=(), **profile_kw):
    fake = ExpectedProtocol(CONFIG_2CH + list(extra))
    adc = StreamingADC(fake, profile(**profile_kw))
    adc.configure(10_000, ["pressure", "valve_position"], block_samples=4)
    return fake, adc


# ------------------------------------------------------------------ codec


def test_crc_is_ccitt_false():
    assert crc16(b"123456789") == 0x29B1
    assert crc16(b"") == 0xFFFF


def test_frame_bytes_exact():
    f = encode_frame(0x0102, 0x1122334455, 0b0101, np.array([[1, -1], [0x1234, -32768]]), FLAG_OVERRUN)
    body = bytes.fromhex(
        "a55a"  # sync
        "01"  # type: data
        "01"  # flags: overrun
        "0201"  # seq 0x0102, little-endian
        "05"  # channel mask: inputs 0 and 2
        "02"  # 2 samples per channel
        "5544332211000000"  # first sample index, u64 LE
        "0100" "ffff" "3412" "0080"  # s0c0 s0c1 s1c0 s1c1, int16 LE
    )
    assert f[:-2] == body
    assert f[-2:] == crc16(body[2:]).to_bytes(2, "little")
    assert len(f) == 16 + 2 * 2 * 2 + 2


def test_actual_rate_is_master_clock_divided():
    assert actual_rate(10_000) == 10_000
    assert actual_rate(3000) == pytest.approx(10e6 / 3333)


# ------------------------------------------------------------------ commands


def test_configure_sends_exact_commands():
    fake, adc = configured()
    fake.assert_done()
    assert adc.config.rate_hz == 10_000
    assert [c.name for c in adc.config.channels] == ["pressure", "valve_position"]
    assert adc.config.frame_len == 16 + 2 * 4 * 2 + 2


def test_configure_uses_actual_rate_from_reply_and_orders_channels():
    fake = ExpectedProtocol([
        (b"STOP\n", b"OK STOP 0\n"),
        (b"RATE 3000\n", b"OK RATE 3000.3\n"),
        (b"CHAN 1,3\n", b"OK CHAN 1,3\n"),
        (b"RANGE 1 25MA\n", b"OK RANGE 1 25MA\n"),
        (b"RANGE 3 25MA\n", b"OK RANGE 3 25MA\n"),
        (b"BLOCK 15\n", b"OK BLOCK 15\n"),
    ])
    adc = StreamingADC(fake, profile())
    cfg = adc.configure(3000, ["spare_3", "valve_position"])
    fake.assert_done()
    assert cfg.rate_hz == 3000.3
    assert cfg.mask == 0b1010 and cfg.block_samples == 15  # auto: ~200 frames/s


def test_stop_skips_an_old_stream_before_its_reply():
    junk = frame(7, 28, counts(28), mask=0b1111)[:30] + b"\x00\xa5\x5a\x01" + bytes(range(40))
    fake = ExpectedProtocol([(b"STOP\n", junk + b"OK STOP 32\r\n")] + CONFIG_2CH[1:])
    adc = StreamingADC(fake, profile())
    adc.configure(10_000, ["pressure", "valve_position"], block_samples=4)
    fake.assert_done()


def test_identify():
    fake = ExpectedProtocol([(b"*IDN?\n", b"OK VELAB,SADC-4,SN42,1.0\r\n")])
    assert StreamingADC(fake, profile()).identify() == "VELAB,SADC-4,SN42,1.0"


def test_error_reply_is_device_exception_with_code():
    fake = ExpectedProtocol([(b"STOP\n", b"OK STOP 0\n"), (b"RATE 10000\n", b"ERR 2 BAD ARGUMENT: rate must be 100..50000\n")])
    adc = StreamingADC(fake, profile())
    with pytest.raises(DeviceException) as ei:
        adc.configure(10_000, ["pressure"], block_samples=4)
    assert ei.value.code == 2 and "rate must be" in str(ei.value)


def test_unknown_command_error_code_1():
    fake = ExpectedProtocol([(b"FOO\n", b"ERR 1 UNKNOWN COMMAND\n")])
    with pytest.raises(DeviceException) as ei:
        StreamingADC(fake, profile()).command("FOO")
    assert ei.value.code == 1


def test_garbled_reply_is_protocol_error():
    fake = ExpectedProtocol([(b"*IDN?\n", b"HELLO\n")])
    with pytest.raises(ProtocolError):
        StreamingADC(fake, profile()).identify()


def test_missing_reply_is_timeout():
    fake = ExpectedProtocol([(b"*IDN?\n", b"OK VELAB")])  # no terminator
    t = time.monotonic()
    with pytest.raises(DeviceTimeout, match="no reply"):
        StreamingADC(fake, profile(command_timeout_s=0.2)).identify()
    assert time.monotonic() - t < 5


def test_commands_refused_while_streaming():
    fake, adc = configured([(b"START\n", b"OK START\n"), (b"STOP\n", b"OK STOP 0\n")])
    adc.start()
    with pytest.raises(DeviceException) as ei:
        adc.command("RATE 1000")
    assert ei.value.code == 3
    adc.stop()
    fake.assert_done()


# ------------------------------------------------------------------ frames -> samples


def test_frames_to_samples_exact():
    frames = b"".join(frame(n, 4 * n, counts(4 * n)) for n in range(3))
    fake, adc = configured([(b"START\n", b"OK START\n" + frames), (b"STOP\n", b"OK STOP 12\n")])
    t_before = time.time()
    adc.start()
    got = []
    while sum(b.n for b in got) < 12:
        got.append(adc.get_block(timeout=2))
    stats = adc.stop()
    fake.assert_done()
    raw = np.concatenate([b.raw for b in got])
    np.testing.assert_array_equal(raw, counts(0, 12))
    b = got[0]
    assert b.first_index == 0 and b.lost_before == 0 and b.segment == 0 and not b.restarted
    assert b.channels == ("pressure", "valve_position") and b.units == ("Pa", "%")
    assert b.host_time_s >= t_before
    np.testing.assert_allclose(np.concatenate([b.device_time_s for b in got]), np.arange(12) / 10_000)
    # counts -> mA -> engineering values
    sig = raw * 25.0 / 32767
    np.testing.assert_allclose(np.concatenate([b.signal for b in got]), sig)
    np.testing.assert_allclose(np.concatenate([b.values for b in got])[:, 0], (sig[:, 0] - 4) / 16 * 6e5)
    np.testing.assert_allclose(np.concatenate([b.values for b in got])[:, 1], (sig[:, 1] - 4) / 16 * 100)
    np.testing.assert_allclose(got[0].head_m("pressure"), pressure_to_head_m(got[0].values[:, 0]))
    assert stats.samples == 12 and stats.lost == 0 and stats.crc_errors == 0 and stats.frames == 3


def run_stream(stream: bytes, stop_total: int, **start_kw):
    # the fake device is silent after its frames until STOP: a data timeout that the test thread's way to
    # STOP cannot reach on a loaded host (0.5 s did: StreamSilent in a loaded pair)
    fake, adc = configured([(b"START\n", b"OK START\n"), (b"STOP\n", f"OK STOP {stop_total}\n".encode())],
                           data_timeout_s=60.0)
    adc.start(**start_kw)
    fake.feed(stream)
    deadline = time.monotonic() + 5
    while fake.rx and time.monotonic() < deadline:
        time.sleep(0.01)
    stats = adc.stop()  # its reply comes after the frames: the reader has taken every one before it
    fake.assert_done()
    return adc, stats


def test_sequence_gap_counted_exactly_and_reported_on_the_block():
    stream = frame(0, 0, counts(0)) + frame(3, 12, counts(12)) + frame(4, 16, counts(16))  # frames 1, 2 lost
    adc, stats = run_stream(stream, 20)
    blocks = adc.get_blocks()
    assert [(b.first_index, b.n, b.lost_before) for b in blocks] == [(0, 4, 0), (12, 8, 8)]
    assert stats.lost == 8 and stats.samples == 12


def test_tail_loss_counted_from_stop_reply():
    adc, stats = run_stream(frame(0, 0, counts(0)), 12)  # device made 12, we got 4
    assert stats.lost == 8 and stats.samples == 4


def test_corrupted_frames_resync_and_count():
    good = [frame(n, 4 * n, counts(4 * n)) for n in range(8)]
    bad1 = bytearray(good[2]); bad1[20] ^= 0x40  # payload bit flip -> CRC
    bad2 = bytearray(good[4]); del bad2[10:13]  # three bytes lost
    bad3 = bytearray(good[6]); bad3[6] = 0x0F  # header: wrong channel mask
    stream = (b"\x00\x13" + good[0] + good[1] + bytes(bad1) + good[3] + b"\xa5\x5a\x01\x00junk" + bytes(bad2)
              + good[5] + bytes(bad3) + good[7])
    adc, stats = run_stream(stream, 32)
    raw = np.concatenate([b.raw for b in adc.get_blocks()])
    expected = np.concatenate([counts(4 * n) for n in (0, 1, 3, 5, 7)])
    np.testing.assert_array_equal(raw, expected)  # only intact frames, nothing invented
    assert stats.lost == 12 and stats.samples == 20
    assert stats.crc_errors >= 2 and stats.header_errors >= 1 and stats.resyncs >= 4
    assert stats.discarded_bytes > 0


def test_overrun_flag_and_gap():
    stream = frame(0, 0, counts(0)) + frame(6, 24, counts(24), flags=FLAG_OVERRUN) + frame(7, 28, counts(28))
    adc, stats = run_stream(stream, 32)
    b = adc.get_blocks()
    assert b[1].overrun and b[1].lost_before == 20 and stats.overruns == 1 and stats.lost == 20


def test_stale_frame_discarded():
    stream = frame(0, 0, counts(0)) + frame(1, 4, counts(4)) + frame(0, 0, counts(0)) + frame(2, 8, counts(8))
    adc, stats = run_stream(stream, 12)
    assert stats.stale_frames == 1 and stats.samples == 12 and stats.lost == 0


def test_invalid_and_clipped_counts_become_nan_and_flags():
    raw = np.array([[-32768, 32767], [6554, 1000], [6554, -32767], [6554, 6554]])
    adc, stats = run_stream(frame(0, 0, raw), 4)
    (b,) = adc.get_blocks()
    assert np.isnan(b.values[0, 0]) and np.isnan(b.signal[0, 0])
    assert b.quality == (Quality.NAN, Quality.OPEN_LOOP)  # 1000 counts = 0.76 mA < 3.6 mA
    assert np.isfinite(b.values[1:, 0]).all()


def mA_counts(mA):
    return int(round(mA / 25.0 * 32767))


@pytest.mark.parametrize("mA,quality", [
    (25.0, Quality.SENSOR_FAULT),  # ADC full scale: beyond NE43 20.5 mA
    (22.0, Quality.SENSOR_FAULT),  # a failure-high transmitter: not a pressure ceiling
    (20.4, Quality.OVER_RANGE),  # inside the NE43 band, beyond the span (+2 % margin): a bound
    (20.2, Quality.OK),  # within the range margin
    (3.7, Quality.SENSOR_FAULT),
    (2.0, Quality.OPEN_LOOP),
])
def test_per_sample_loop_quality(mA, quality):
    raw = np.full((4, 2), mA_counts(5.0))
    raw[2, 0] = mA_counts(mA) if mA < 25 else 32767
    adc, _ = run_stream(frame(0, 0, raw), 4)
    b = adc.get_blocks()[0]
    assert b.quality == (quality, Quality.OK)
    expect = np.zeros((4, 2), np.uint8)
    expect[2, 0] = QUALITY_CODE[quality]
    np.testing.assert_array_equal(b.sample_quality, expect)  # per sample, not only per block
    assert b.good(0).tolist() == [True, True, quality.is_measurement, True]


def test_callback_mode():
    got = []
    adc, stats = run_stream(frame(0, 0, counts(0)) + frame(1, 4, counts(4)), 8, callback=got.append)
    assert sum(b.n for b in got) == 8 and stats.samples == 8


def test_a_slow_consumer_is_not_a_silent_device():
    """The data timeout counts the device's silence, not the time the reader spent delivering a block:
    a callback that takes longer than the timeout (a loaded host's consumer) while frames keep coming
    ends in no error (it ended StreamSilent: the last frame's instant was taken before the delivery)."""
    fake, adc = configured([(b"START\n", b"OK START\n"), (b"STOP\n", b"OK STOP 40\n")])
    got, errors, slow = [], [], threading.Event()

    def consume(block):
        got.append(block)
        if not slow.is_set():
            slow.set()
            fake.feed(b"".join(frame(n, 4 * n, counts(4 * n)) for n in range(1, 10)))  # they come meanwhile
            time.sleep(1.5 * adc.profile.data_timeout_s)

    adc.start(callback=consume, on_error=errors.append)
    fake.feed(frame(0, 0, counts(0)))
    deadline = time.monotonic() + 10
    while sum(b.n for b in got) < 40 and not errors and time.monotonic() < deadline:
        time.sleep(0.01)
    # every frame delivered before any error (after the last one the fake is silent: a StreamSilent then is right)
    assert sum(b.n for b in got) == 40, errors
    adc.stop()


class HeldRead(ExpectedProtocol):
    """A port one of whose reads during the stream ends empty ``hold_s`` after the host stopped running the
    reader (a loaded machine): the device's next frames came meanwhile and wait in the port's buffer."""

    def __init__(self, pairs, hold_s):
        super().__init__(pairs)
        self.hold_s, self.held, self.hold = hold_s, False, threading.Event()

    def read(self, size: int = 1) -> bytes:
        if self.hold.is_set() and not self.held and size > 0:
            self.held = True
            time.sleep(self.hold_s)
            return b""
        return super().read(size)


def test_a_reader_held_by_its_host_is_not_a_silent_device():
    """The data timeout counts the time the reader listened: a read that returned empty after the host had
    held the reader 3 x the timeout, while the device sent, is not StreamSilent (a loaded pair's run failed
    "no valid frame for 1 s", 0 bytes discarded); the frames that came meanwhile are read next."""
    fake = HeldRead(CONFIG_2CH + [(b"START\n", b"OK START\n"), (b"STOP\n", b"OK STOP 12\n")], hold_s=1.5)
    adc = StreamingADC(fake, profile(data_timeout_s=0.5))
    adc.configure(10_000, ["pressure", "valve_position"], block_samples=4)
    got, errors = [], []

    def consume(block):
        got.append(block)
        if len(got) == 1:
            fake.hold.set()
            fake.feed(frame(1, 4, counts(4)) + frame(2, 8, counts(8)))  # sent while the reader is held

    adc.start(callback=consume, on_error=errors.append)
    fake.feed(frame(0, 0, counts(0)))
    deadline = time.monotonic() + 10
    while sum(b.n for b in got) < 12 and not errors and time.monotonic() < deadline:
        time.sleep(0.01)
    assert fake.held and errors == [] and sum(b.n for b in got) == 12
    adc.stop()


def test_the_stop_reply_read_after_a_slow_consumer_is_taken():
    """STOP's reply came while the reader was held longer than the command timeout by the consumer of the
    last frames (a loaded host): it is read and taken, not a DeviceTimeout (the time was checked before
    the bytes already waiting were read)."""
    fake, adc = configured([(b"START\n", b"OK START\n"), (b"STOP\n", b"")], data_timeout_s=60.0)
    got = []

    def consume(block):
        got.append(block)
        if len(got) == 2:  # the frame that came after STOP
            time.sleep(2.0 * adc.profile.command_timeout_s)

    adc.start(callback=consume)
    fake.feed(frame(0, 0, counts(0)))
    while not got:
        time.sleep(0.005)
    out = {}
    stopper = threading.Thread(target=lambda: out.setdefault("stats", adc.stop()), daemon=True)
    stopper.start()
    while fake.pairs:  # STOP written
        time.sleep(0.002)
    fake.feed(frame(1, 4, counts(4)))
    while len(got) < 2:
        time.sleep(0.002)
    fake.feed(b"OK STOP 8\n")  # while the consumer holds the reader
    stopper.join(10)
    assert not stopper.is_alive() and "stats" in out, "stop() raised or hung"
    assert out["stats"].samples == 8 and out["stats"].lost == 0


class StarvedDevice(ExpectedProtocol):
    """A port whose first read after STOP ends empty ``hold_s`` after the host stopped running the reader, and
    whose device, kept from running as well (a simulator in the same process), answers STOP only after the
    reader's next read: ``reply`` is waiting from the third read after STOP on."""

    def __init__(self, pairs, hold_s, reply):
        super().__init__(pairs)
        self.hold_s, self.reply, self.reads_after_stop = hold_s, reply, 0

    def read(self, size: int = 1) -> bytes:
        if self.written[-2:] == [b"START\n", b"STOP\n"] and size > 0:  # (configure's STOP is not this one)
            self.reads_after_stop += 1
            if self.reads_after_stop == 1:
                time.sleep(self.hold_s)
                return b""
            if self.reads_after_stop == 3:
                self.feed(self.reply)
        return super().read(size)


def test_a_stop_reply_after_the_host_held_reader_and_device_is_taken():
    """The wait for STOP's reply counts the time the reader listened: a pass the host held it 2.5 x the command
    timeout, then an empty read (the device had not run either), then the reply: taken, not a DeviceTimeout (a
    loaded pair: "no reply to 'STOP' within 1 s" from an unpaced simulator in the test's process)."""
    fake = StarvedDevice([(b"START\n", b"OK START\n"), (b"STOP\n", b"")], hold_s=2.5 * 0.3, reply=b"OK STOP 4\n")
    fake.pairs[:0] = CONFIG_2CH
    adc = StreamingADC(fake, profile(command_timeout_s=0.3, data_timeout_s=60.0))
    adc.configure(10_000, ["pressure", "valve_position"], block_samples=4)
    got = []
    adc.start(callback=got.append)
    fake.feed(frame(0, 0, counts(0)))
    while not got:
        time.sleep(0.005)
    stats = adc.stop()
    assert fake.reads_after_stop >= 3 and stats.samples == 4 and stats.lost == 0


class SlowDrain(ExpectedProtocol):
    """A port that hands over at most one frame a read, each read ``per_read_s`` of a loaded host's time; after
    STOP, ``endless``: the device streams on (a frame added at each read), else nothing more comes."""

    def __init__(self, pairs, frame_len, per_read_s, endless=False):
        super().__init__(pairs)
        self.frame_len, self.per_read_s, self.endless, self.seq = frame_len, per_read_s, endless, 0

    def read(self, size: int = 1) -> bytes:
        stopping = self.written[-2:] == [b"START\n", b"STOP\n"]
        if stopping and size > 0:
            time.sleep(self.per_read_s)
            if self.endless:
                self.seq += 1
                self.feed(frame(self.seq, 4 * self.seq, counts(4 * self.seq)))
        return super().read(min(size, self.frame_len) if stopping else size)


def _stop_behind(n_frames, endless=False):
    """The host fell ``n_frames`` frames behind (all received, not yet read) when it sent STOP (they become
    readable as it is written, so the reader cannot have taken them before)."""
    backlog = b"".join(frame(n, 4 * n, counts(4 * n)) for n in range(n_frames))
    reply = b"" if endless else b"OK STOP %d\n" % (4 * n_frames)
    fake = SlowDrain(CONFIG_2CH + [(b"START\n", b"OK START\n"), (b"STOP\n", backlog + reply)],
                     len(frame(0, 0, counts(0))), per_read_s=0.05, endless=endless)
    adc = StreamingADC(fake, profile(command_timeout_s=0.2, data_timeout_s=60.0))  # 1 s of frames after STOP
    adc.configure(10_000, ["pressure", "valve_position"], block_samples=4)
    adc.start(callback=lambda b: None)
    return adc


def test_frames_received_before_stop_went_out_do_not_count_against_its_reply():
    """40 frames already received when STOP is sent, read one a pass at 0.05 s (2 s, beyond the 1 s bound of
    frames after STOP): the device sent them before it could see STOP, so its reply after them is taken."""
    adc = _stop_behind(40)
    stats = adc.stop()
    assert stats.lost == 0 and stats.samples == 160


def test_a_device_that_streams_on_after_stop_is_named():
    adc = _stop_behind(4, endless=True)
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match="no reply to 'STOP' within 1 s of frames"):
        adc.stop()
    assert time.monotonic() - t0 < 5.0


def test_a_stop_never_answered_names_the_device_s_silence():
    fake, adc = configured([(b"START\n", b"OK START\n"), (b"STOP\n", b"")], data_timeout_s=60.0)
    adc.start()
    with pytest.raises(DeviceTimeout, match="no reply to 'STOP' within 0.3 s of the device's silence"):
        adc.stop()


class LateWaker(ExpectedProtocol):
    """A port whose reads after the first STOP time out empty, for 2 x the command timeout, just as its reply
    arrives: a reader thread kept from running while the bytes came (a loaded host)."""

    def __init__(self, pairs, hold_s):
        super().__init__(pairs)
        self.hold_s, self.held = hold_s, False

    def read(self, size: int = 1) -> bytes:
        if self.written[-1:] == [b"STOP\n"] and not self.held and size > 0:
            self.held = True
            with self.lock:
                reply, self.rx[:] = bytes(self.rx), b""
            time.sleep(self.hold_s)
            with self.lock:
                self.rx += reply  # it came while this read was ending
            return b""
        return super().read(size)


def test_the_configure_stop_reply_that_came_while_the_reader_was_held_is_taken():
    fake = LateWaker(CONFIG_2CH, hold_s=2 * 0.3)
    adc = StreamingADC(fake, profile(command_timeout_s=0.3))
    cfg = adc.configure(10_000, ["pressure", "valve_position"], block_samples=4)
    assert fake.held and cfg.rate_hz == 10_000
    fake.assert_done()


def test_silent_stream_ends_in_device_timeout():
    fake, adc = configured([(b"START\n", b"OK START\n"), (b"STOP\n", b"")])
    errors = []
    adc.start(on_error=errors.append)
    with pytest.raises(DeviceTimeout):
        adc.get_block(timeout=5)
    assert isinstance(errors[0], DeviceTimeout) and adc.error is errors[0]
    adc.stop()  # the reader is already gone: returns, no hang


def test_garbage_only_stream_is_timeout_not_data():
    fake, adc = configured([(b"START\n", b"OK START\n"), (b"STOP\n", b"")])
    adc.start()
    rng = np.random.default_rng(3)
    stop = threading.Event()

    def spew():
        while not stop.is_set():
            fake.feed(rng.integers(0, 256, 200, dtype=np.uint8).tobytes())
            time.sleep(0.01)

    th = threading.Thread(target=spew, daemon=True)
    th.start()
    with pytest.raises(DeviceTimeout, match="no valid frame"):
        adc.get_block(timeout=5)
    stop.set()
    th.join()
    assert adc.stats.samples == 0


# ------------------------------------------------------------------ parser property


def test_parser_bytewise_equals_bulk_and_never_invents():
    rng = np.random.default_rng(7)
    sent, stream = [], bytearray()
    for n in range(300):
        f = bytearray(frame(n, 4 * n, rng.integers(-32767, 32767, (4, 2))))
        r = rng.random()
        if r < 0.1:
            f[int(rng.integers(0, len(f)))] ^= int(rng.integers(1, 256))
        elif r < 0.15:
            a = int(rng.integers(0, len(f) - 3))
            del f[a : a + 3]
        else:
            sent.append(bytes(f))
        stream += f
        if rng.random() < 0.1:
            stream += rng.integers(0, 256, int(rng.integers(1, 30)), dtype=np.uint8).tobytes()
    p1, p2 = FrameParser(0b11, 4), FrameParser(0b11, 4)
    bulk = p1.feed(bytes(stream))[0]
    bytewise = [f for i in range(len(stream)) for f in p2.feed(stream[i : i + 1])[0]]
    assert bulk == bytewise
    good = {f[16:-2] for f in sent}
    assert all(f.payload in good for f in bulk)
    assert len(bulk) >= len(sent) - 3  # junk may occasionally hide a frame behind a false start


# ------------------------------------------------------------------ profile


def test_builtin_profile_loads():
    p = load_profile("streaming_adc")
    assert p.rate_hz == 10_000 and p.enabled == ("pressure", "valve_position")
    assert p.channel("pressure").calibration.units == "Pa" and p.channel("pressure").head
    assert p.channel(1).name == "valve_position"


GOOD = """
[acquisition]
rate_hz = 5000
channels = ["p"]
[channels.p]
index = 0
signal_lo = 4
signal_hi = 20
value_lo = 0
value_hi = 1e6
units = "Pa"
"""


@pytest.mark.parametrize(
    "edit, key",
    [
        (("rate_hz = 5000", "rate_hz = 60000"), "acquisition.rate_hz"),
        (("rate_hz = 5000", "rate_hz = \"fast\""), "acquisition.rate_hz"),
        (('channels = ["p"]', 'channels = ["q"]'), "acquisition.channels"),
        (("index = 0", "index = 7"), "channels.p.index"),
        (("signal_hi = 20", "signal_hi = 2"), "channels.p.signal_hi"),
        (("units = \"Pa\"", "units = \"Pa\"\nrange = \"5MA\""), "channels.p.range"),
        (("units = \"Pa\"", "units = \"Pa\"\ngain = 2"), "channels.p.gain"),
        (("[acquisition]", "[aquisition]"), "aquisition"),
    ],
)
def test_profile_errors_are_one_line_with_file_and_key(tmp_path, edit, key):
    path = tmp_path / "adc.toml"
    path.write_text(GOOD.replace(*edit))
    with pytest.raises(StreamingADCProfileError) as ei:
        load_profile(path)
    msg = str(ei.value)
    assert "\n" not in msg and str(path) in msg and key in msg
    assert isinstance(ei.value, ConfigError)  # the CLI prints it as a user error


def test_profile_good_file_and_missing_file(tmp_path):
    path = tmp_path / "adc.toml"
    path.write_text(GOOD)
    p = load_profile(path)
    assert p.rate_hz == 5000 and p.channel("p").calibration.open_loop_below == 3.6
    with pytest.raises(StreamingADCProfileError, match="no such file"):
        load_profile(tmp_path / "nope.toml")


# ------------------------------------------------------------------ several sections (a transducer on input 2)


def test_a_pressure_source_of_two_sections_acquires_input_2_byte_exact():
    """The pressure source asked for the valve's transducer and the one on input 2 (the bench's
    [recorder.transducers]): one CHAN and one RANGE more, and each block carries input 2 as a pressure."""
    from dataclasses import replace

    from velab.drivers.pressure_source import StreamingSource

    prof = replace(load_profile("streaming_adc_sections"), command_timeout_s=0.3, data_timeout_s=0.5,
                   reconnect=False, poll_s=0.01)
    k = 50  # one frame of the BLOCK size below
    i = np.arange(k)
    raw = np.stack([13000 + i, 16000 + i, 14000 + i], axis=1)  # inputs 0, 1, 2: sample i of each
    fake = ExpectedProtocol([
        (b"STOP\n", b"OK STOP 0\n"),
        (b"RATE 10000\n", b"OK RATE 10000\n"),
        (b"CHAN 0,1,2\n", b"OK CHAN 0,1,2\n"),
        (b"RANGE 0 25MA\n", b"OK RANGE 0 25MA\n"),
        (b"RANGE 1 25MA\n", b"OK RANGE 1 25MA\n"),
        (b"RANGE 2 25MA\n", b"OK RANGE 2 25MA\n"),
        (b"BLOCK 50\n", b"OK BLOCK 50\n"),  # ~200 frames/s of 10 kHz
        (b"START\n", b"OK START\n" + frame(0, 0, raw, mask=0b111)),
        (b"STOP\n", b"OK STOP 50\n"),
    ])
    src = StreamingSource(StreamingADC(fake, prof, name="adc"), "adc")
    assert src.pressure_channels() == ("pressure", "pressure_2", "pressure_3")
    src.configure(10_000, ("pressure", "pressure_2"))
    assert src.start() == 10_000
    r = src.read_blocks(wait_s=2.0)
    src.stop()
    fake.assert_done()
    (b,) = r.blocks
    assert b.channels == ("pressure", "valve_position", "pressure_2") and b.units == ("Pa", "%", "Pa")
    sig = raw * 25.0 / 32767
    np.testing.assert_allclose(b.column("pressure_2"), (sig[:, 2] - 4) / 16 * 6e5)
    np.testing.assert_allclose(b.head_m("pressure_2"), pressure_to_head_m(b.column("pressure_2")))
    assert b.sample_quality.shape == (k, 3) and not b.sample_quality.any()
