"""What every driver shares: readings with units, time and quality; typed errors;
the analogue-loop calibration that turns raw signals into pressure and head.

Qt-free and I/O-free: drivers build on it, the recorder and GUI consume it.
"""

from __future__ import annotations

import enum
import math
import time
from dataclasses import dataclass

GRAVITY_M_S2 = 9.81


class Quality(enum.Enum):
    OK = "ok"
    OVER_RANGE = "over_range"
    UNDER_RANGE = "under_range"
    OPEN_LOOP = "open_loop"  # 4-20 mA loop below 3.6 mA (NAMUR NE43)
    STALE = "stale"  # the device did not refresh the value in time
    NAN = "nan"  # the device reported NaN or an invalid value
    FAULT = "fault"  # the device flags an alarm


@dataclass(frozen=True)
class Reading:
    """One value from a device, in engineering units."""

    value: float
    units: str
    timestamp_s: float  # host time (time.time()) unless device_time_s says otherwise
    quality: Quality = Quality.OK
    device_time_s: float | None = None
    raw: int | float | None = None

    @property
    def ok(self) -> bool:
        return self.quality is Quality.OK


def host_time() -> float:
    return time.time()


# ----------------------------------------------------------------- errors


class DeviceError(Exception):
    """Base of every device-layer error; the message names the device and what failed."""


class DeviceTimeout(DeviceError):
    """The device did not answer within the configured timeout (after retries)."""


class DeviceDisconnected(DeviceError):
    """The transport is closed or the peer went away."""


class ProtocolError(DeviceError):
    """A reply was malformed: bad CRC, wrong length, wrong function code, bad frame."""


class DeviceException(DeviceError):
    """The device answered with an error (e.g. a Modbus exception reply)."""

    def __init__(self, message: str, code: int | None = None):
        super().__init__(message)
        self.code = code


class DeviceFault(DeviceError):
    """The device reports a fault state (e.g. the valve actuator's fault bits)."""


class ProfileError(DeviceError):
    """A device profile (TOML) is invalid; the message names file and key."""


# ----------------------------------------------------------------- calibration


@dataclass(frozen=True)
class LoopCalibration:
    """Linear analogue loop: signal (mA or V) -> engineering value.

    For a 4-20 mA pressure transducer over 0..6 bar: signal_lo=4, signal_hi=20,
    value_lo=0, value_hi=6e5 (Pa). ``zero_offset`` is subtracted from the value
    (transducer zero drift, found with the pipe at atmospheric pressure).
    """

    signal_lo: float
    signal_hi: float
    value_lo: float
    value_hi: float
    units: str = "Pa"
    signal_units: str = "mA"
    zero_offset: float = 0.0
    open_loop_below: float | None = 3.6  # mA; None for voltage inputs
    range_margin: float = 0.0  # fraction of span tolerated beyond the ends before flagging

    def value(self, signal: float) -> float:
        frac = (signal - self.signal_lo) / (self.signal_hi - self.signal_lo)
        return self.value_lo + frac * (self.value_hi - self.value_lo) - self.zero_offset

    def signal(self, value: float) -> float:
        frac = (value + self.zero_offset - self.value_lo) / (self.value_hi - self.value_lo)
        return self.signal_lo + frac * (self.signal_hi - self.signal_lo)

    def quality(self, signal: float) -> Quality:
        if signal is None or (isinstance(signal, float) and math.isnan(signal)):
            return Quality.NAN
        if self.open_loop_below is not None and signal < self.open_loop_below:
            return Quality.OPEN_LOOP
        span = self.signal_hi - self.signal_lo
        if signal > self.signal_hi + self.range_margin * span:
            return Quality.OVER_RANGE
        if signal < self.signal_lo - self.range_margin * span:
            return Quality.UNDER_RANGE
        return Quality.OK


def pressure_to_head_m(pressure_pa: float, density_kg_m3: float = 998.2) -> float:
    """Gauge pressure (Pa) to pressure head (m of water column)."""
    return pressure_pa / (density_kg_m3 * GRAVITY_M_S2)


def head_to_pressure_pa(head_m: float, density_kg_m3: float = 998.2) -> float:
    return head_m * density_kg_m3 * GRAVITY_M_S2
