"""LabJack T-series spontaneous stream packets and the T7's binary -> volts calibration (pure, no I/O).

Stream data over Ethernet (T-series datasheet 3.2.4 "Low-Level Stream", "Data Collection"): with
STREAM_AUTO_TARGET bit 0 set the device sends each packet, as soon as STREAM_SAMPLES_PER_PACKET samples are
buffered, to the host's TCP connection on port 702. A packet is a Modbus-TCP-like frame, big endian::

    bytes 0-1   transaction id: 0 for the first packet after STREAM_ENABLE = 1, +1 per packet (wraps at 2^16)
    bytes 2-3   protocol id, 0
    bytes 4-5   length of what follows byte 5 (unit id .. last sample) = 10 + 2 x samples
    byte  6     unit id, 1
    byte  7     function 76 (0x4C, LabJack's Modbus Feedback)
    byte  8     16 (the stream packet type)
    byte  9     reserved
    bytes 10-11 backlog: bytes still in the device's stream buffer after this packet
    bytes 12-13 status code (0, or STREAM_* of velab.drivers.labjack_registers.STREAM_STATUS)
    bytes 14-15 additional status information (STREAM_AUTO_RECOVER_END: the number of scans skipped)
    bytes 16..  samples, 2 bytes each, scan after scan in scan-list order (AIN: 16-bit binary)

Auto-recovery (the same section; LabJack's C examples): when the buffer fills, the device discards new scans
and keeps sending what it holds (status 2940); when the buffer has room again the next packet carries status
2941 with the count of skipped scans and one dummy scan of 0xFFFF samples between the old and the new data.
This layout agrees with two independent hosts: NSchrading/async_labjack (src/helpers/stream.rs) and LabJack's
own Arduino/C stream examples (spontaneousStreamRead: 16-byte header, type byte 16, transaction id check).

AIN stream samples are the high-speed converter's binary; the host applies the factory calibration constants
(datasheet 20.0.1 "T7 Calibration Constants", in internal flash at 0x3C4000)::

    volts = (binary - center) x positive_slope   if binary >= center
            (center - binary) x negative_slope   otherwise
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from velab.drivers.base import FrameError, ProtocolError

HEADER = struct.Struct(">HHHBBBBHHH")  # tid, protocol, length, unit, function, type, reserved, backlog, status, info
HEADER_LEN = HEADER.size  # 16
STREAM_FUNCTION = 76
STREAM_TYPE = 16
LENGTH_OVERHEAD = 10  # unit, function, type, reserved, backlog, status, additional
DUMMY_SAMPLE = 0xFFFF  # the separator scan of STREAM_AUTO_RECOVER_END
MAX_SAMPLES_PER_PACKET = 512  # LabJack's examples: "Max is 512" over TCP


@dataclass(frozen=True)
class StreamPacket:
    tid: int
    backlog_bytes: int
    status: int
    additional: int
    samples: np.ndarray  # uint16, as sent (scans interleaved)


def encode_packet(tid: int, samples, *, backlog_bytes: int = 0, status: int = 0, additional: int = 0,
                  unit: int = 1) -> bytes:
    """One spontaneous stream packet as the device sends it (the simulator's and the tests' encoder)."""
    data = np.asarray(samples, dtype=">u2").tobytes()
    head = HEADER.pack(tid & 0xFFFF, 0, LENGTH_OVERHEAD + len(data), unit, STREAM_FUNCTION, STREAM_TYPE, 0,
                       min(int(backlog_bytes), 0xFFFF), status, additional & 0xFFFF)
    return head + data


class PacketReader:
    """Splits the bytes of the 702 connection into packets; a header that is not a stream packet's is a
    FrameError (TCP carries no resynchronisation marker: the rest of the connection cannot be trusted)."""

    def __init__(self, name: str = "labjack stream"):
        self.name = name
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[StreamPacket]:
        self._buf += data
        out = []
        while len(self._buf) >= HEADER_LEN:
            tid, proto, length, _unit, fc, kind, _res, backlog, status, info = HEADER.unpack_from(self._buf)
            if proto != 0 or fc != STREAM_FUNCTION or kind != STREAM_TYPE or length < LENGTH_OVERHEAD \
                    or (length - LENGTH_OVERHEAD) % 2:
                head = bytes(self._buf[:HEADER_LEN]).hex(" ")
                raise FrameError(f"{self.name}: not a stream packet header ({head}): protocol {proto}, "
                                 f"function {fc}, type {kind}, length {length}", device=self.name,
                                 reason="bad_header")
            total = 6 + length
            if len(self._buf) < total:
                break
            samples = np.frombuffer(bytes(self._buf[HEADER_LEN:total]), dtype=">u2").astype(np.uint16)
            del self._buf[:total]
            out.append(StreamPacket(tid, backlog, status, info, samples))
        return out

    @property
    def pending(self) -> int:
        return len(self._buf)


# ------------------------------------------------------------------ T7 calibration

T7_RANGES = {10.0: 0, 1.0: 1, 0.1: 2, 0.01: 3}  # AIN#_RANGE (+-V) -> gain index (x1, x10, x100, x1000)
# datasheet 20.0.1, nominal +-10 V high-speed constants (also async_labjack's T7AinCalibration defaults)
T7_NOMINAL_GAIN1 = (0.000315805780, -0.000315805800, 33523.0, -10.586956522)


@dataclass(frozen=True)
class T7Calibration:
    """The high-speed converter's (positive slope, negative slope, binary center, offset) per gain index;
    stream data always comes from it."""

    hs: tuple[tuple[float, float, float, float], ...]
    source: str = "device"  # "device" (read from flash) or "nominal"

    @classmethod
    def from_floats(cls, values) -> "T7Calibration":
        """From the 41 flash floats (the first 16: HS gain 1/10/100/1000 x (PSlope, NSlope, Center, Offset))."""
        v = [float(x) for x in values]
        if len(v) < 16:
            raise ProtocolError(f"T7 calibration: {len(v)} constants, expected at least 16")
        hs = tuple(tuple(v[4 * g:4 * g + 4]) for g in range(4))
        for g, (ps, ns, center, _off) in enumerate(hs):
            # an erased flash reads 0xFFFFFFFF (NaN); a slope of the wrong sign is not a calibration
            if not (np.isfinite([ps, ns, center]).all() and ps > 0 > ns and 0 < center < 65536):
                raise ProtocolError(f"T7 calibration: gain index {g} constants implausible "
                                    f"(PSlope {ps:g}, NSlope {ns:g}, Center {center:g})")
        return cls(hs, "device")

    @classmethod
    def nominal(cls) -> "T7Calibration":
        """The datasheet's nominal +-10 V constants (only gain index 0: other ranges need the device's)."""
        return cls((T7_NOMINAL_GAIN1,), "nominal")

    def _gain(self, gain_index: int):
        if gain_index >= len(self.hs):
            raise ValueError(f"T7 calibration ({self.source}) has no constants for gain index {gain_index}: "
                             f"use the +-10 V range or read the device's calibration")
        return self.hs[gain_index]

    def volts(self, binary, gain_index: int = 0) -> np.ndarray:
        ps, ns, center, _ = self._gain(gain_index)
        b = np.asarray(binary, dtype=float)
        return np.where(b >= center, (b - center) * ps, (center - b) * ns)

    def binary(self, volts, gain_index: int = 0) -> np.ndarray:
        """The inverse (the simulator's converter): the nearest 16-bit code, clipped to 0..65535."""
        ps, ns, center, _ = self._gain(gain_index)
        v = np.asarray(volts, dtype=float)
        b = np.where(v >= 0, center + v / ps, center - v / ns)
        return np.clip(np.round(b), 0, 65535).astype(np.uint16)

    def to_floats(self) -> list[float]:
        """The 41 flash floats (HS constants; HR, DAC, temperature and currents zero): the simulator's flash."""
        v = [x for g in self.hs for x in g]
        v += list(self.hs[0]) * (4 - len(self.hs))
        return v + [0.0] * (41 - len(v))
