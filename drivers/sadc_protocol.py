"""SADC-4 streaming-ADC wire protocol (docs/devices-streaming-adc.md): constants, frame codec,
and the resynchronising byte-stream parser. Pure functions, no I/O: the host driver
(velab.drivers.streaming_adc) and the device simulator (velab.simulators.streaming_adc)
both use them.
"""

from __future__ import annotations

import binascii
import math
import re
import struct
from dataclasses import dataclass

import numpy as np

__all__ = [
    "CRC_INIT", "CRC_LEN", "ERROR_NAMES", "ERR_BAD_ARGUMENT", "ERR_BUSY", "ERR_HARDWARE", "ERR_LINE_TOO_LONG",
    "ERR_LINK_TOO_SLOW", "ERR_UNKNOWN_COMMAND", "FLAG_CLIP", "FLAG_INVALID", "FLAG_OVERRUN", "FRAME_DATA", "Frame",
    "FrameParser", "HEADER", "HEADER_LEN", "MASTER_CLOCK_HZ", "MAX_BLOCK", "MAX_CHANNELS", "MAX_LINE", "RANGES_FS",
    "RATE_MAX_HZ", "RATE_MIN_HZ", "RAW_FULL_SCALE", "RAW_INVALID", "SYNC", "actual_rate", "auto_block",
    "channel_mask", "crc16", "encode_frame", "frame_length", "mask_channels",
]

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
