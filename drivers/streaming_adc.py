"""Serial streaming ADC (VELAB SADC-4 protocol): hardware-clocked, 1-4 channels.

The wire protocol is specified in ``docs/devices-streaming-adc.md``; this module
is its reference implementation on the host side (the simulator in
``velab.simulators.streaming_adc`` is the device side and reuses the codec here).

Qt-free. The transport is injected: a pyserial URL or path (real port, pty,
``socket://host:port``, ``loop://``) opened with :func:`serial.serial_for_url`,
or an already-open serial-like object (``read``, ``write``, ``in_waiting``,
``timeout``; ``open``/``close`` for reconnection).

Typical use (the recorder's view)::

    profile = load_profile("streaming_adc")          # configs/devices/streaming_adc.toml
    with StreamingADC(profile.url, profile) as adc:
        adc.configure()                              # rate, channels, ranges from the profile
        adc.start()                                  # reader thread -> bounded queue
        while recording:
            block = adc.get_block(timeout=1.0)       # SampleBlock, or a typed DeviceError
        adc.stop()
        print(adc.stats)

Nothing here invents samples: lost samples are counted from the device's sample
counter (exact), reconnection gaps are estimated from host time and flagged,
invalid ADC conversions become NaN with ``Quality.NAN``.
"""

from __future__ import annotations

import binascii
import math
import queue
import re
import struct
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from velab.drivers.base import (
    DeviceDisconnected,
    DeviceError,
    DeviceException,
    DeviceTimeout,
    LoopCalibration,
    ProfileError,
    ProtocolError,
    Quality,
    pressure_to_head_m,
)
from velab.drivers.blocks import SampleBlock
from velab.config import CONFIG_ROOT, read_toml
from velab.errors import ConfigError

# ============================================================== protocol constants

SYNC = b"\xa5\x5a"
FRAME_DATA = 0x01
HEADER = struct.Struct("<2sBBHBBQ")  # sync, type, flags, seq, channel mask, samples/frame, first index
HEADER_LEN = HEADER.size  # 16
CRC_LEN = 2
CRC_INIT = 0xFFFF  # CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, xorout 0

FLAG_OVERRUN = 0x01  # frames were discarded (device FIFO full) immediately before this one
FLAG_CLIP = 0x02  # at least one sample of this frame is at +/- full scale
FLAG_INVALID = 0x04  # at least one sample is the invalid-conversion code

RAW_INVALID = -32768  # the ADC could not convert (input NaN / open / fault)
RAW_FULL_SCALE = 32767  # +FS; -32767 is -FS

MASTER_CLOCK_HZ = 10_000_000  # sample clock = MASTER_CLOCK_HZ / divider
RATE_MIN_HZ, RATE_MAX_HZ = 100, 50_000
MAX_CHANNELS = 4
MAX_BLOCK = 255  # samples per channel per frame
MAX_LINE = 64  # bytes in a command line, terminator included

RANGES_FS = {"25MA": (25.0, "mA"), "10V": (10.0, "V")}  # range code -> (full scale, signal units)

# error codes in "ERR <code> <text>" replies
ERR_UNKNOWN_COMMAND = 1
ERR_BAD_ARGUMENT = 2
ERR_BUSY = 3
ERR_LINE_TOO_LONG = 4
ERR_LINK_TOO_SLOW = 5
ERR_HARDWARE = 6
ERROR_NAMES = {
    ERR_UNKNOWN_COMMAND: "UNKNOWN COMMAND",
    ERR_BAD_ARGUMENT: "BAD ARGUMENT",
    ERR_BUSY: "BUSY",
    ERR_LINE_TOO_LONG: "LINE TOO LONG",
    ERR_LINK_TOO_SLOW: "LINK TOO SLOW",
    ERR_HARDWARE: "HARDWARE FAULT",
}


def crc16(data: bytes | bytearray | memoryview, init: int = CRC_INIT) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF); check("123456789") == 0x29B1."""
    return binascii.crc_hqx(data, init)


def actual_rate(rate_hz: float) -> float:
    """The sample rate the device really runs at: master clock / integer divider."""
    divider = max(1, round(MASTER_CLOCK_HZ / rate_hz))
    return MASTER_CLOCK_HZ / divider


def channel_mask(channels) -> int:
    mask = 0
    for c in channels:
        mask |= 1 << c
    return mask


def mask_channels(mask: int) -> list[int]:
    return [c for c in range(MAX_CHANNELS) if mask >> c & 1]


def frame_length(n_channels: int, block: int) -> int:
    return HEADER_LEN + 2 * n_channels * block + CRC_LEN


def encode_frame(seq: int, first_index: int, mask: int, raw: np.ndarray, flags: int = 0) -> bytes:
    """One data frame; ``raw`` is (block, n_channels) int16 in ascending channel order."""
    raw = np.ascontiguousarray(raw, dtype="<i2")
    block = raw.shape[0]
    body = HEADER.pack(SYNC, FRAME_DATA, flags, seq & 0xFFFF, mask, block, first_index) + raw.tobytes()
    return body + crc16(body[2:]).to_bytes(2, "little")


def auto_block(rate_hz: float, n_channels: int) -> int:
    """Samples per frame for ~200 frames/s, within the 255-sample frame limit."""
    return int(min(MAX_BLOCK, max(1, math.ceil(rate_hz / 200.0))))


@dataclass(frozen=True)
class Frame:
    flags: int
    seq: int
    first_index: int
    payload: bytes  # block * n_channels little-endian int16, sample-major


_CANDIDATE = re.compile(rb"\xa5\x5a|OK|ERR")
_STOP_REPLY = re.compile(rb"OK STOP (\d+)\r?\n")


class FrameParser:
    """Incremental byte-stream parser: data frames and ASCII reply lines, with resync.

    At a boundary the next bytes must be a frame (``A5 5A``) or a reply line
    (``OK``/``ERR`` ... ``\\n``). Anything else, a header that does not match the
    configured channel mask / block, or a CRC mismatch, makes the parser skip
    forward to the next candidate (counted in ``resyncs``; skipped bytes in
    ``discarded_bytes``). A damaged frame is dropped whole, never repaired.
    """

    def __init__(self, mask: int, block: int):
        self.mask = mask
        self.block = block
        self.frame_len = frame_length(len(mask_channels(mask)), block)
        self.buf = bytearray()
        self.crc_errors = 0
        self.header_errors = 0
        self.resyncs = 0
        self.discarded_bytes = 0
        self._hunting = False

    def feed(self, data: bytes) -> tuple[list[Frame], list[str]]:
        buf = self.buf
        buf += data
        frames: list[Frame] = []
        lines: list[str] = []
        pos = 0
        n = len(buf)
        fl = self.frame_len
        while n - pos >= 2:
            b0 = buf[pos]
            bad = False
            if b0 == 0xA5 and buf[pos + 1] == 0x5A:
                avail = n - pos
                if avail >= 8 and (buf[pos + 2] != FRAME_DATA or buf[pos + 6] != self.mask or buf[pos + 7] != self.block):
                    self.header_errors += 1
                    bad = True
                elif avail < fl:
                    break
                else:
                    end = pos + fl
                    if binascii.crc_hqx(memoryview(buf)[pos + 2 : end - 2], CRC_INIT) != buf[end - 2] | buf[end - 1] << 8:
                        self.crc_errors += 1
                        bad = True
                    else:
                        _, _, flags, seq, _, _, first = HEADER.unpack_from(buf, pos)
                        frames.append(Frame(flags, seq, first, bytes(buf[pos + HEADER_LEN : end - 2])))
                        pos = end
                        self._hunting = False
                        continue
            elif b0 == 0x4F or b0 == 0x45:  # 'O' / 'E': maybe a reply line
                nl = buf.find(b"\n", pos, pos + MAX_LINE + 8)
                if nl < 0:
                    if n - pos < MAX_LINE + 8 and (buf.startswith(b"OK", pos) or buf.startswith(b"ER", pos)):
                        break  # wait for the rest of the line
                    bad = True
                else:
                    line = bytes(buf[pos:nl]).rstrip(b"\r")
                    if (line.startswith(b"OK") or line.startswith(b"ERR")) and line.isascii():
                        lines.append(line.decode("ascii"))
                        pos = nl + 1
                        self._hunting = False
                        continue
                    bad = True
            else:
                bad = True
            # resynchronise: skip to the next frame or line candidate
            if not self._hunting:
                self._hunting = True
                self.resyncs += 1
            m = _CANDIDATE.search(buf, pos + 1)
            nxt = m.start() if m else max(pos + 1, n - 1)
            self.discarded_bytes += nxt - pos
            pos = nxt
        del buf[:pos]
        return frames, lines


# ============================================================== profile


class StreamingADCProfileError(ProfileError, ConfigError):
    """A streaming-ADC profile is invalid (a DeviceError and a user-facing ConfigError)."""


@dataclass(frozen=True)
class ChannelProfile:
    name: str
    index: int  # ADC input 0..3
    range: str  # "25MA" or "10V"
    calibration: LoopCalibration
    head: bool = False  # also offer pressure head (m) for this channel (values in Pa)

    @property
    def full_scale(self) -> float:
        return RANGES_FS[self.range][0]


@dataclass(frozen=True)
class StreamingADCProfile:
    channels: tuple[ChannelProfile, ...]  # every defined input
    enabled: tuple[str, ...]  # names acquired by default, in any order
    rate_hz: float = 10_000.0
    block_samples: int = 0  # 0 = auto
    url: str | None = None
    baudrate: int = 921_600
    model: str = "VELAB SADC-4"
    command_timeout_s: float = 1.0
    data_timeout_s: float = 2.0
    reconnect: bool = True
    reconnect_timeout_s: float = 10.0
    poll_s: float = 0.05
    queue_blocks: int = 2000
    density_kg_m3: float = 998.2
    path: Path | None = None

    def channel(self, key: str | int) -> ChannelProfile:
        for ch in self.channels:
            if ch.name == key or ch.index == key:
                return ch
        raise KeyError(f"no channel {key!r} in the streaming ADC profile (have {', '.join(c.name for c in self.channels)})")


def default_profile(**overrides) -> StreamingADCProfile:
    """A built-in profile (no file): pressure 4-20 mA = 0..6 bar, valve 4-20 mA = 0..100 %, two spares."""
    chans = (
        ChannelProfile("pressure", 0, "25MA", LoopCalibration(4.0, 20.0, 0.0, 6.0e5, "Pa", range_margin=0.02), head=True),
        ChannelProfile("valve_position", 1, "25MA", LoopCalibration(4.0, 20.0, 0.0, 100.0, "%", range_margin=0.02)),
        ChannelProfile("spare_2", 2, "25MA", LoopCalibration(4.0, 20.0, 4.0, 20.0, "mA")),
        ChannelProfile("spare_3", 3, "25MA", LoopCalibration(4.0, 20.0, 4.0, 20.0, "mA")),
    )
    base = StreamingADCProfile(channels=chans, enabled=("pressure", "valve_position"))
    return replace(base, **overrides)


_REQUIRED = object()


class _TomlReader:
    def __init__(self, path: Path):
        self.path = path

    def fail(self, key: str, reason: str) -> StreamingADCProfileError:
        return StreamingADCProfileError(f"{self.path}: {key}: {reason}")

    def table(self, doc: dict, name: str, allowed: set[str], required: bool = False) -> dict:
        t = doc.get(name, None)
        if t is None:
            if required:
                raise self.fail(name, "missing table")
            return {}
        if not isinstance(t, dict):
            raise self.fail(name, "must be a table")
        for k in t:
            if k not in allowed:
                raise self.fail(f"{name}.{k}", f"unknown key (allowed: {', '.join(sorted(allowed))})")
        return t

    def get(self, t: dict, where: str, key: str, kind, default=_REQUIRED, check=None):
        full = f"{where}.{key}"
        if key not in t:
            if default is _REQUIRED:
                raise self.fail(full, "missing")
            return default
        v = t[key]
        if kind is float and isinstance(v, int) and not isinstance(v, bool):
            v = float(v)
        if kind is int and isinstance(v, bool) or not isinstance(v, kind):
            raise self.fail(full, f"must be {kind.__name__}, got {type(v).__name__} {v!r}")
        if check is not None:
            msg = check(v)
            if msg:
                raise self.fail(full, msg)
        return v


def _pos(v):
    return None if v > 0 else "must be positive"


def load_profile(name_or_path: str | Path = "streaming_adc") -> StreamingADCProfile:
    """Load ``configs/devices/<name>.toml`` (or a path) into a typed profile.

    Every error is one line naming the file and the key.
    """
    p = Path(name_or_path)
    if not (p.suffix == ".toml" or p.exists() or len(p.parts) > 1):
        p = CONFIG_ROOT / "devices" / f"{name_or_path}.toml"
    try:
        path, doc = read_toml(p)
    except ConfigError as exc:
        raise StreamingADCProfileError(str(exc)) from None
    r = _TomlReader(path)
    for k in doc:
        if k not in {"device", "acquisition", "timeouts", "reader", "fluid", "channels"}:
            raise r.fail(k, "unknown table")
    dev = r.table(doc, "device", {"model", "url", "baudrate"})
    acq = r.table(doc, "acquisition", {"rate_hz", "channels", "block_samples"}, required=True)
    tmo = r.table(doc, "timeouts", {"command_s", "data_s", "reconnect", "reconnect_s", "poll_s"})
    rdr = r.table(doc, "reader", {"queue_blocks"})
    fluid = r.table(doc, "fluid", {"density_kg_m3"})
    chans_doc = r.table(doc, "channels", set(doc.get("channels", {}) if isinstance(doc.get("channels"), dict) else ()), required=True)

    chans: list[ChannelProfile] = []
    used: dict[int, str] = {}
    ch_keys = {"index", "range", "signal_lo", "signal_hi", "value_lo", "value_hi", "units", "zero_offset",
               "open_loop_below", "range_margin", "head"}
    for name, cd in chans_doc.items():
        where = f"channels.{name}"
        if not isinstance(cd, dict):
            raise r.fail(where, "must be a table")
        for k in cd:
            if k not in ch_keys:
                raise r.fail(f"{where}.{k}", f"unknown key (allowed: {', '.join(sorted(ch_keys))})")
        idx = r.get(cd, where, "index", int, check=lambda v: None if 0 <= v < MAX_CHANNELS else "must be 0..3")
        if idx in used:
            raise r.fail(f"{where}.index", f"input {idx} is already used by channels.{used[idx]}")
        used[idx] = name
        rng = r.get(cd, where, "range", str, "25MA", check=lambda v: None if v in RANGES_FS else f"must be one of {', '.join(RANGES_FS)}")
        s_lo = r.get(cd, where, "signal_lo", float)
        s_hi = r.get(cd, where, "signal_hi", float)
        if s_hi <= s_lo:
            raise r.fail(f"{where}.signal_hi", "must be greater than signal_lo")
        if max(abs(s_lo), abs(s_hi)) > RANGES_FS[rng][0]:
            raise r.fail(f"{where}.signal_hi", f"outside the {rng} input range")
        v_lo = r.get(cd, where, "value_lo", float)
        v_hi = r.get(cd, where, "value_hi", float)
        if v_hi == v_lo:
            raise r.fail(f"{where}.value_hi", "must differ from value_lo")
        units = r.get(cd, where, "units", str)
        zero = r.get(cd, where, "zero_offset", float, 0.0)
        olb_default = 3.6 if rng.endswith("MA") else None
        olb = r.get(cd, where, "open_loop_below", float, olb_default)
        margin = r.get(cd, where, "range_margin", float, 0.0, check=lambda v: None if 0 <= v < 1 else "must be in [0, 1)")
        head = r.get(cd, where, "head", bool, False)
        if head and units != "Pa":
            raise r.fail(f"{where}.head", f"needs units = \"Pa\" (got {units!r})")
        cal = LoopCalibration(s_lo, s_hi, v_lo, v_hi, units, RANGES_FS[rng][1], zero, olb, margin)
        chans.append(ChannelProfile(name, idx, rng, cal, head))
    if not chans:
        raise r.fail("channels", "define at least one channel")

    names = {c.name for c in chans}
    enabled = r.get(acq, "acquisition", "channels", list)
    if not enabled or len(enabled) > MAX_CHANNELS:
        raise r.fail("acquisition.channels", "list 1 to 4 channel names")
    for e in enabled:
        if e not in names:
            raise r.fail("acquisition.channels", f"{e!r} is not defined under [channels] (have {', '.join(sorted(names))})")
    if len(set(enabled)) != len(enabled):
        raise r.fail("acquisition.channels", "lists a channel twice")
    rate = r.get(acq, "acquisition", "rate_hz", float,
                 check=lambda v: None if RATE_MIN_HZ <= v <= RATE_MAX_HZ else f"must be {RATE_MIN_HZ}..{RATE_MAX_HZ} Hz")
    block = r.get(acq, "acquisition", "block_samples", int, 0,
                  check=lambda v: None if 0 <= v <= MAX_BLOCK else f"must be 0 (auto) .. {MAX_BLOCK}")
    url = r.get(dev, "device", "url", str, None)
    return StreamingADCProfile(
        channels=tuple(chans),
        enabled=tuple(enabled),
        rate_hz=rate,
        block_samples=block,
        url=url or None,
        baudrate=r.get(dev, "device", "baudrate", int, 921_600, check=_pos),
        model=r.get(dev, "device", "model", str, "VELAB SADC-4"),
        command_timeout_s=r.get(tmo, "timeouts", "command_s", float, 1.0, check=_pos),
        data_timeout_s=r.get(tmo, "timeouts", "data_s", float, 2.0, check=_pos),
        reconnect=r.get(tmo, "timeouts", "reconnect", bool, True),
        reconnect_timeout_s=r.get(tmo, "timeouts", "reconnect_s", float, 10.0, check=_pos),
        poll_s=r.get(tmo, "timeouts", "poll_s", float, 0.05, check=lambda v: None if 0 < v <= 1 else "must be in (0, 1] s"),
        queue_blocks=r.get(rdr, "reader", "queue_blocks", int, 2000, check=_pos),
        density_kg_m3=r.get(fluid, "fluid", "density_kg_m3", float, 998.2, check=_pos),
        path=path,
    )


# ============================================================== data delivered


# SampleBlock: velab.drivers.blocks (shared with the Modbus ADC)


@dataclass
class StreamStats:
    samples: int = 0  # samples per channel delivered
    blocks: int = 0
    frames: int = 0
    lost: int = 0  # exact, from device sample-counter gaps (incl. the tail reported by STOP)
    lost_estimated: int = 0  # reconnection gaps, estimated from host time
    queue_dropped: int = 0  # samples dropped because the consumer's queue was full
    overruns: int = 0  # frames flagged OVERRUN by the device
    crc_errors: int = 0
    header_errors: int = 0
    resyncs: int = 0
    discarded_bytes: int = 0
    reconnects: int = 0
    stale_frames: int = 0  # CRC-valid frames whose counter went backwards (discarded)
    bytes_read: int = 0


@dataclass(frozen=True)
class AcquisitionConfig:
    rate_hz: float  # actual device rate (from the RATE reply)
    channels: tuple[ChannelProfile, ...]  # ascending input order
    block_samples: int

    @property
    def mask(self) -> int:
        return channel_mask(c.index for c in self.channels)

    @property
    def frame_len(self) -> int:
        return frame_length(len(self.channels), self.block_samples)


# ============================================================== the driver

_ERR_REPLY = re.compile(r"ERR (\d+)(?: (.*))?$")


class StreamingADC:
    """Host driver for the SADC-4 streaming ADC. See the module docstring."""

    def __init__(self, transport: Any = None, profile: StreamingADCProfile | None = None, *, name: str = "streaming ADC"):
        self.profile = profile or default_profile()
        transport = transport if transport is not None else self.profile.url
        if transport is None:
            raise ValueError("StreamingADC needs a transport URL/path, a serial-like object, or a profile with device.url")
        self._url = transport if isinstance(transport, (str, Path)) else None
        self._port = None if self._url is not None else transport
        self.name = name
        self.config: AcquisitionConfig | None = None
        self._stats = StreamStats()
        self._stats_lock = threading.Lock()
        self._rx = bytearray()  # bytes read past a reply line, handed to the stream parser
        self._thread: threading.Thread | None = None
        self._stop_evt = threading.Event()
        self._queue: queue.Queue | None = None
        self._callback: Callable[[SampleBlock], None] | None = None
        self._on_error: Callable[[DeviceError], None] | None = None
        self.error: DeviceError | None = None
        self._streaming = False
        self._stop_error: DeviceError | None = None
        self._parser: FrameParser | None = None
        self._seg_base_stats: tuple = ()
        self._segment = 0

    # ---------------------------------------------------------------- transport

    def open(self) -> None:
        if self._port is not None and getattr(self._port, "is_open", True):
            return
        if self._url is None:
            try:
                self._port.open()
            except Exception as exc:
                raise DeviceDisconnected(f"{self.name}: cannot reopen port: {exc}") from exc
            return
        import serial

        try:
            self._port = serial.serial_for_url(
                str(self._url), baudrate=self.profile.baudrate, timeout=self.profile.poll_s,
                write_timeout=self.profile.command_timeout_s,
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceDisconnected(f"{self.name}: cannot open {self._url}: {exc}") from exc

    def close(self) -> None:
        if self._thread is not None:
            try:
                self.stop()
            except DeviceError:
                pass
        self._close_port()

    def _close_port(self) -> None:
        if self._port is not None:
            try:
                self._port.close()
            except Exception:
                pass
        if self._url is not None:
            self._port = None
        self._rx.clear()

    def __enter__(self) -> "StreamingADC":
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _write(self, data: bytes) -> None:
        if self._port is None:
            raise DeviceDisconnected(f"{self.name}: port is not open")
        try:
            self._port.write(data)
        except Exception as exc:  # SerialException, SerialTimeoutException, OSError
            if type(exc).__name__ == "SerialTimeoutException":
                raise DeviceTimeout(f"{self.name}: write of {data!r} timed out") from exc
            raise DeviceDisconnected(f"{self.name}: write failed: {exc}") from exc

    def _read(self, size: int) -> bytes:
        if self._port is None:
            raise DeviceDisconnected(f"{self.name}: port is not open")
        try:
            n = self._port.in_waiting
            return self._port.read(max(n, size))
        except Exception as exc:
            raise DeviceDisconnected(f"{self.name}: read failed: {exc}") from exc

    # ---------------------------------------------------------------- commands

    def command(self, line: str) -> str:
        """Send one command line; return the reply text after ``OK`` (maybe empty).

        ``ERR <code> <text>`` raises DeviceException(code); no reply within
        ``command_timeout_s`` raises DeviceTimeout; a reply that is neither OK
        nor ERR raises ProtocolError. Not allowed while streaming.
        """
        if self._streaming:
            raise DeviceException(f"{self.name}: {line!r} refused: streaming (stop first)", ERR_BUSY)
        if self._port is None:
            self.open()
        self._write(line.encode("ascii") + b"\n")
        reply = self._read_line(line)
        return self._check_reply(line, reply)

    def _check_reply(self, line: str, reply: str) -> str:
        if reply == "OK" or reply.startswith("OK "):
            return reply[3:]
        m = _ERR_REPLY.match(reply)
        if m:
            code = int(m.group(1))
            raise DeviceException(f"{self.name}: {line!r} -> error {code} {m.group(2) or ERROR_NAMES.get(code, '')}".rstrip(), code)
        raise ProtocolError(f"{self.name}: {line!r} -> unexpected reply {reply!r}")

    def _read_line(self, what: str) -> str:
        deadline = time.monotonic() + self.profile.command_timeout_s
        while True:
            nl = self._rx.find(b"\n")
            if nl >= 0:
                raw = bytes(self._rx[:nl]).rstrip(b"\r")
                del self._rx[: nl + 1]
                try:
                    return raw.decode("ascii")
                except UnicodeDecodeError:
                    raise ProtocolError(f"{self.name}: {what!r} -> non-ASCII reply {raw!r}") from None
            if len(self._rx) > 4 * MAX_LINE:
                raise ProtocolError(f"{self.name}: {what!r} -> no line terminator in {bytes(self._rx[:32])!r}...")
            if time.monotonic() > deadline:
                got = f" (got {bytes(self._rx)!r})" if self._rx else ""
                raise DeviceTimeout(f"{self.name}: no reply to {what!r} within {self.profile.command_timeout_s:g} s{got}")
            self._rx += self._read(1)

    def _stop_idle(self) -> int:
        """Send STOP outside streaming and skip anything (old frames) until its reply."""
        self._write(b"STOP\n")
        deadline = time.monotonic() + self.profile.command_timeout_s
        while True:
            m = _STOP_REPLY.search(self._rx)
            if m:
                total = int(m.group(1))
                del self._rx[: m.end()]
                return total
            e = re.search(rb"ERR (\d+)[^\n]*\n", self._rx)
            if e:
                line = bytes(e.group(0)).decode("ascii", "replace").strip()
                del self._rx[: e.end()]
                self._check_reply("STOP", line)
            if time.monotonic() > deadline:
                raise DeviceTimeout(f"{self.name}: no reply to 'STOP' within {self.profile.command_timeout_s:g} s")
            self._rx += self._read(64)
            if len(self._rx) > 1 << 20:
                del self._rx[: -MAX_LINE]

    def identify(self) -> str:
        return self.command("*IDN?")

    def configure(self, rate_hz: float | None = None, channels=None, block_samples: int | None = None) -> AcquisitionConfig:
        """Stop any stream, then set rate, channels, ranges and frame size.

        ``channels``: names or input indices (default: the profile's list).
        Returns the configuration the device accepted (actual rate from its reply).
        """
        if self._streaming:
            raise DeviceException(f"{self.name}: configure() while streaming (stop first)", ERR_BUSY)
        prof = self.profile
        rate = float(rate_hz if rate_hz is not None else prof.rate_hz)
        if not RATE_MIN_HZ <= rate <= RATE_MAX_HZ:
            raise ValueError(f"rate_hz must be {RATE_MIN_HZ}..{RATE_MAX_HZ}, got {rate}")
        keys = channels if channels is not None else prof.enabled
        chans = sorted({prof.channel(k).index: prof.channel(k) for k in keys}.values(), key=lambda c: c.index)
        if not 1 <= len(chans) <= MAX_CHANNELS:
            raise ValueError("acquire 1 to 4 channels")
        block = block_samples if block_samples is not None else prof.block_samples
        if not block:
            block = auto_block(rate, len(chans))
        if not 1 <= block <= MAX_BLOCK:
            raise ValueError(f"block_samples must be 1..{MAX_BLOCK}")
        self.open()
        self._stop_idle()
        reply = self.command(f"RATE {rate:.10g}")
        try:
            actual = float(reply.split()[1])
        except (IndexError, ValueError):
            raise ProtocolError(f"{self.name}: 'RATE' -> unexpected reply 'OK {reply}'") from None
        self.command("CHAN " + ",".join(str(c.index) for c in chans))
        for c in chans:
            self.command(f"RANGE {c.index} {c.range}")
        self.command(f"BLOCK {block}")
        self.config = AcquisitionConfig(actual, tuple(chans), block)
        return self.config

    # ---------------------------------------------------------------- streaming

    def start(self, callback: Callable[[SampleBlock], None] | None = None,
              on_error: Callable[[DeviceError], None] | None = None, *, wait_when_full: bool = False) -> None:
        """Start the stream and the reader thread.

        With ``callback`` each SampleBlock is passed to it (in the reader thread,
        keep it short); otherwise blocks go to a bounded queue read with
        :meth:`get_block`. A fatal error (DeviceTimeout, DeviceDisconnected after
        failed reconnection, ...) ends the reader; it is raised by ``get_block``
        and passed to ``on_error``, and kept in ``self.error``.

        Queue full (the consumer is too slow): by default the block is dropped,
        counted in ``stats.queue_dropped`` and reported as ``lost_before`` of the
        next block. With ``wait_when_full=True`` the reader waits instead, so the
        back-pressure reaches the device, whose FIFO overrun is then counted
        exactly from its sample counter.
        """
        if self._thread is not None:
            raise DeviceException(f"{self.name}: already streaming", ERR_BUSY)
        if self.config is None:
            self.configure()
        self._callback = callback
        self._on_error = on_error
        self._wait_when_full = wait_when_full
        self._queue = queue.Queue(maxsize=self.profile.queue_blocks) if callback is None else None
        self.error = None
        self._stop_error = None
        with self._stats_lock:
            self._stats = StreamStats()
        self._segment = 0
        self._start_stream()
        self._stop_evt.clear()
        self._thread = threading.Thread(target=self._run, name=f"{self.name} reader", daemon=True)
        self._thread.start()

    def _start_stream(self) -> None:
        self.command("START")
        cfg = self.config
        self._parser = FrameParser(cfg.mask, cfg.block_samples)
        self._expected = 0
        self._pending_lost = 0
        self._pending_restart = False
        self._streaming = True
        self._last_frame_mono = time.monotonic()
        self._last_frame_host = time.time()
        self._seg_base_stats = (0, 0, 0, 0)

    def get_block(self, timeout: float | None = None) -> SampleBlock:
        """Next block from the queue. Raises the reader's fatal error, or
        DeviceTimeout if nothing arrives within ``timeout`` (default: data timeout)."""
        if self._queue is None:
            raise DeviceException(f"{self.name}: not started in queue mode")
        timeout = self.profile.data_timeout_s if timeout is None else timeout
        try:
            item = self._queue.get(timeout=timeout)
        except queue.Empty:
            if self.error is not None:
                raise self.error
            if self._thread is None or not self._thread.is_alive():
                raise DeviceException(f"{self.name}: stream is stopped")
            raise DeviceTimeout(f"{self.name}: no sample block within {timeout:g} s") from None
        if isinstance(item, BaseException):
            raise item
        if item is None:
            raise DeviceException(f"{self.name}: stream is stopped")
        return item

    def get_blocks(self) -> list[SampleBlock]:
        """Every block queued so far, without waiting (raises a pending fatal error)."""
        out = []
        while self._queue is not None:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                break
            if isinstance(item, BaseException):
                if out:  # deliver data first; keep the error for the next call
                    self._queue.put(item)
                    break
                raise item
            if item is not None:
                out.append(item)
        return out

    def stop(self) -> StreamStats:
        """Stop the stream (STOP, wait for its acknowledgement, count the tail) and the reader.

        Returns the final stats. Raises DeviceTimeout if the device did not
        acknowledge STOP; a fatal error that already ended the reader is not
        raised again (it was delivered, and stays in ``self.error``).
        """
        t = self._thread
        if t is None:
            return self.stats
        self._stop_evt.set()
        t.join(self.profile.poll_s * 4 + self.profile.command_timeout_s + 2.0)
        alive = t.is_alive()
        self._thread = None
        self._streaming = False
        if self._queue is not None:
            try:
                self._queue.put_nowait(None)
            except queue.Full:
                pass
        if alive:
            raise DeviceTimeout(f"{self.name}: reader thread did not finish")
        if self._stop_error is not None:
            raise self._stop_error
        return self.stats

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    @property
    def stats(self) -> StreamStats:
        with self._stats_lock:
            s = replace(self._stats)
        p = getattr(self, "_parser", None)
        if p is not None and self._seg_base_stats:
            b = self._seg_base_stats
            s.crc_errors += p.crc_errors - b[0]
            s.header_errors += p.header_errors - b[1]
            s.resyncs += p.resyncs - b[2]
            s.discarded_bytes += p.discarded_bytes - b[3]
        return s

    # ---------------------------------------------------------------- reader thread

    def _run(self) -> None:
        prof = self.profile
        cfg = self.config
        # read about half a poll period of data per call (at least a frame): big blocks, bounded latency
        per_s = cfg.rate_hz / cfg.block_samples * cfg.frame_len
        chunk = int(max(cfg.frame_len, min(1 << 16, per_s * prof.poll_s / 2)))
        try:
            if self._rx:  # bytes that followed the START reply
                data, self._rx = bytes(self._rx), bytearray()
                self._process(data, time.time())
            while not self._stop_evt.is_set():
                try:
                    data = self._read(chunk)
                except DeviceDisconnected as exc:
                    if not prof.reconnect:
                        raise
                    self._reconnect(exc)
                    continue
                if data:
                    self._process(data, time.time())
                if time.monotonic() - self._last_frame_mono > prof.data_timeout_s:
                    p = self._parser
                    raise DeviceTimeout(
                        f"{self.name}: no valid frame for {prof.data_timeout_s:g} s "
                        f"({p.crc_errors} CRC errors, {p.discarded_bytes} bytes discarded)"
                    )
            self._stop_streaming()
        except DeviceError as exc:
            self._fail(exc)
        except Exception as exc:  # a bug or a callback error: still end cleanly and report
            err = DeviceError(f"{self.name}: reader failed: {type(exc).__name__}: {exc}")
            err.__cause__ = exc
            self._fail(err)
        finally:
            self._streaming = False

    def _fail(self, exc: DeviceError) -> None:
        self.error = exc
        try:  # best effort: leave the device idle
            if self._port is not None and not isinstance(exc, DeviceDisconnected):
                self._port.write(b"STOP\n")
        except Exception:
            pass
        if self._queue is not None:
            try:
                self._queue.put_nowait(exc)
            except queue.Full:  # make room: the error matters more than the oldest block
                try:
                    self._queue.get_nowait()
                except queue.Empty:
                    pass
                self._queue.put_nowait(exc)
        if self._on_error is not None:
            try:
                self._on_error(exc)
            except Exception:
                pass

    def _stop_streaming(self) -> None:
        """In the reader thread: send STOP, keep parsing frames until ``OK STOP <n>``."""
        self._write(b"STOP\n")
        deadline = time.monotonic() + self.profile.command_timeout_s
        while time.monotonic() < deadline:
            try:
                data = self._read(self.config.frame_len)
            except DeviceDisconnected as exc:
                self._stop_error = exc
                return
            if data:
                total = self._process(data, time.time(), stopping=True)
                if total is not None:
                    tail = total - self._expected
                    if tail > 0:
                        with self._stats_lock:
                            self._stats.lost += tail
                        self._expected = total
                    return
        m = _STOP_REPLY.search(self._parser.buf)
        if m:
            tail = int(m.group(1)) - self._expected
            if tail > 0:
                with self._stats_lock:
                    self._stats.lost += tail
            return
        self._stop_error = DeviceTimeout(f"{self.name}: no reply to 'STOP' within {self.profile.command_timeout_s:g} s")

    def _reconnect(self, cause: DeviceDisconnected) -> None:
        prof = self.profile
        deadline = time.monotonic() + prof.reconnect_timeout_s
        delay = 0.05
        last_exc: Exception = cause
        self._streaming = False
        p = self._parser
        b = self._seg_base_stats
        with self._stats_lock:  # fold this segment's parser counters into the stats
            self._stats.crc_errors += p.crc_errors - b[0]
            self._stats.header_errors += p.header_errors - b[1]
            self._stats.resyncs += p.resyncs - b[2]
            self._stats.discarded_bytes += p.discarded_bytes - b[3]
        self._seg_base_stats = ()
        last_host = self._last_frame_host
        while not self._stop_evt.is_set():
            if time.monotonic() > deadline:
                raise DeviceDisconnected(
                    f"{self.name}: disconnected and could not reconnect within {prof.reconnect_timeout_s:g} s: {last_exc}"
                ) from cause
            self._close_port()
            time.sleep(delay)
            delay = min(delay * 2, 0.5)
            try:
                self.open()
                cfg = self.config
                self.configure(cfg.rate_hz, [c.index for c in cfg.channels], cfg.block_samples)
                self._start_stream()
            except (DeviceError, ProtocolError) as exc:
                last_exc = exc
                continue
            gap_s = max(0.0, time.time() - last_host)
            est = int(round(gap_s * self.config.rate_hz))
            self._segment += 1
            self._pending_lost = est
            self._pending_restart = True
            with self._stats_lock:
                self._stats.reconnects += 1
                self._stats.lost_estimated += est
            if self._rx:
                data, self._rx = bytes(self._rx), bytearray()
                self._process(data, time.time())
            return
        self._streaming = False

    def _process(self, data: bytes, host_t: float, stopping: bool = False) -> int | None:
        """Parse bytes, build and deliver blocks. Returns the STOP total if its reply was seen."""
        frames, lines = self._parser.feed(data)
        stop_total = None
        for ln in lines:
            m = re.match(r"OK STOP (\d+)$", ln)
            if m and stopping:
                stop_total = int(m.group(1))
        with self._stats_lock:
            self._stats.bytes_read += len(data)
        if frames:
            self._last_frame_mono = time.monotonic()
            self._last_frame_host = host_t
            self._deliver(frames, host_t)
        return stop_total

    def _deliver(self, frames: list[Frame], host_t: float) -> None:
        cfg = self.config
        k = cfg.block_samples
        run: list[Frame] = []
        run_lost = 0
        run_overrun = False
        lost_total = 0
        stale = 0
        overruns = 0
        blocks: list[SampleBlock] = []
        for f in frames:
            if f.first_index < self._expected:
                stale += 1  # counter went backwards: not ours to trust
                continue
            gap = f.first_index - self._expected
            if f.flags & FLAG_OVERRUN:
                overruns += 1
            if (gap or f.flags & FLAG_OVERRUN) and run:
                blocks.append(self._make_block(run, run_lost, run_overrun, host_t))
                run = []
            if not run:
                run_lost = gap
                run_overrun = bool(f.flags & FLAG_OVERRUN)
            lost_total += gap
            run.append(f)
            self._expected = f.first_index + k
        if run:
            blocks.append(self._make_block(run, run_lost, run_overrun, host_t))
        with self._stats_lock:
            st = self._stats
            st.frames += len(frames) - stale
            st.stale_frames += stale
            st.lost += lost_total
            st.overruns += overruns
        for b in blocks:
            self._emit(b)

    def _make_block(self, run: list[Frame], lost: int, overrun: bool, host_t: float) -> SampleBlock:
        cfg = self.config
        chans = cfg.channels
        nch = len(chans)
        raw = np.frombuffer(b"".join(f.payload for f in run), dtype="<i2").reshape(-1, nch)
        flags = 0
        for f in run:
            flags |= f.flags
        fs = np.array([c.full_scale for c in chans])
        invalid = raw == RAW_INVALID
        signal = raw * (fs / RAW_FULL_SCALE)
        if flags & FLAG_INVALID or invalid.any():
            signal[invalid] = np.nan
        cals = [c.calibration for c in chans]
        s_lo = np.array([c.signal_lo for c in cals])
        s_hi = np.array([c.signal_hi for c in cals])
        v_lo = np.array([c.value_lo for c in cals])
        v_hi = np.array([c.value_hi for c in cals])
        zero = np.array([c.zero_offset for c in cals])
        values = v_lo + (signal - s_lo) / (s_hi - s_lo) * (v_hi - v_lo) - zero
        quality = tuple(_column_quality(raw[:, j], signal[:, j], cals[j]) for j in range(nch))
        lost_before = lost + self._pending_lost
        restarted = self._pending_restart
        self._pending_lost = 0
        self._pending_restart = False
        return SampleBlock(
            segment=self._segment, first_index=run[0].first_index, rate_hz=cfg.rate_hz, host_time_s=host_t,
            raw=raw, signal=signal, values=values, channels=tuple(c.name for c in chans),
            units=tuple(c.units for c in cals), quality=quality, lost_before=lost_before,
            restarted=restarted, overrun=overrun, flags=flags, density_kg_m3=self.profile.density_kg_m3,
        )

    def _emit(self, block: SampleBlock) -> None:
        if self._callback is not None:
            self._callback(block)
            with self._stats_lock:
                self._stats.samples += block.n
                self._stats.blocks += 1
            return
        try:
            self._queue.put_nowait(block)
        except queue.Full:
            while self._wait_when_full and not self._stop_evt.is_set():
                try:
                    self._queue.put(block, timeout=self.profile.poll_s)
                except queue.Full:
                    continue
                with self._stats_lock:
                    self._stats.samples += block.n
                    self._stats.blocks += 1
                return
            # the consumer is too slow: drop this block, report it as a gap on the next one
            self._pending_lost += block.lost_before + block.n
            with self._stats_lock:
                self._stats.queue_dropped += block.n
            return
        with self._stats_lock:
            self._stats.samples += block.n
            self._stats.blocks += 1


_Q_ORDER = (Quality.NAN, Quality.OPEN_LOOP, Quality.OVER_RANGE, Quality.UNDER_RANGE)


def _column_quality(raw: np.ndarray, signal: np.ndarray, cal: LoopCalibration) -> Quality:
    if (raw == RAW_INVALID).any():
        return Quality.NAN
    if cal.open_loop_below is not None and (signal < cal.open_loop_below).any():
        return Quality.OPEN_LOOP
    span = cal.signal_hi - cal.signal_lo
    if (raw == RAW_FULL_SCALE).any() or (signal > cal.signal_hi + cal.range_margin * span).any():
        return Quality.OVER_RANGE
    if (raw == -RAW_FULL_SCALE).any() or (signal < cal.signal_lo - cal.range_margin * span).any():
        return Quality.UNDER_RANGE
    return Quality.OK


__all__ = [
    "AcquisitionConfig", "ChannelProfile", "Frame", "FrameParser", "SampleBlock", "StreamStats",
    "StreamingADC", "StreamingADCProfile", "StreamingADCProfileError", "actual_rate", "auto_block",
    "channel_mask", "crc16", "default_profile", "encode_frame", "frame_length", "load_profile", "mask_channels",
]


# ---------------------------------------------------------------- bench registration

_BENCH_KEYS = {"url", "port", "rate_hz", "block_samples", "baudrate", "name"}


def _bench_factory(dev, connect: bool = True) -> "StreamingADC":
    """``[devices.X] kind = "streaming_adc"``: ``url`` (or ``port``) = pyserial URL / path;
    optional ``rate_hz``, ``block_samples``, ``baudrate`` override the profile."""
    from velab.drivers.base import ProfileError

    unknown = sorted(set(dev.settings) - _BENCH_KEYS)
    if unknown:
        raise ProfileError(f"[devices.{dev.name}]: unknown key {unknown[0]!r} (known: {', '.join(sorted(_BENCH_KEYS))})")
    prof = load_profile(dev.profile or "streaming_adc")
    over = {}
    url = dev.settings.get("url") or dev.settings.get("port")
    if url:
        over["url"] = str(url)
    for k in ("rate_hz", "block_samples", "baudrate"):
        if k in dev.settings:
            over[k] = type(getattr(prof, k))(dev.settings[k])
    prof = replace(prof, **over)
    if not prof.url:
        raise ProfileError(f"[devices.{dev.name}] url: missing (a pyserial URL such as socket://host:port or a port path)")
    adc = StreamingADC(prof.url, prof, name=str(dev.settings.get("name", dev.name)))
    if connect:
        adc.open()
    return adc


def _register_bench() -> None:
    from velab.drivers.bench import register_driver

    register_driver("streaming_adc", _bench_factory)


_register_bench()
