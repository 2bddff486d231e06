"""What every driver shares: readings with units, time and quality; named errors;
the analogue-loop calibration that turns raw signals into pressure and head.

Qt-free and I/O-free: drivers build on it, the recorder and GUI consume it.

Errors (the table in docs/devices.md maps each to a run outcome)::

    DeviceError                    .device (who), .reason (a fixed word, see REASONS)
      DeviceTimeout                no reply / no data within the timeout (after retries)
        StreamSilent               a streaming device sent no valid frame for data_s
      DeviceDisconnected           transport closed, refused or vanished
      ProtocolError                a reply that cannot be trusted (never used)
        ChecksumError              bad CRC
        FrameError                 short / long frame, bad header, wrong byte count
        ReplyMismatch              wrong function code, unit id, transaction id or write echo
        ImplausibleReply           well-formed but impossible content (unknown state code)
      DeviceException              the device refused (Modbus exception reply, ERR line); .code
      DeviceFault                  the device reports a fault (valve FAULT state, fault bits)
      DeviceReset                  the device restarted under us (sample counter went backwards)
      TriggerNotStarted            the valve did not start the manoeuvre (read back after a lost reply)
        TriggerRefused             ... because it refused TRIGGER (also a DeviceException, .code)
      TriggerUnknown               the TRIGGER reply was lost and the state could not be read back
      ProfileError                 a device profile / bench table is invalid (also a ConfigError)
"""

from __future__ import annotations

import enum
import math
import time
from dataclasses import dataclass

from velab.errors import ConfigError

GRAVITY_M_S2 = 9.81

# NAMUR NE43 (4-20 mA loops): 3.8..20.5 mA is the measuring band; outside it the
# transmitter signals a failure (<= 3.6 mA, >= 21 mA) or is saturated: not a measurement.
NE43_LOW_MA = 3.8
NE43_HIGH_MA = 20.5
NE43_OPEN_LOOP_MA = 3.6  # below this: broken wire / failure-low signal


class Quality(enum.Enum):
    """Quality of one value. Measurements: OK, OVER_RANGE, UNDER_RANGE (the value is real but
    beyond the calibrated span: a bound). Everything else is *not* a measurement."""

    OK = "ok"
    OVER_RANGE = "over_range"  # above the calibrated span (within the NE43 band): the value is a lower bound
    UNDER_RANGE = "under_range"  # below the calibrated span (within the NE43 band)
    OPEN_LOOP = "open_loop"  # loop current < 3.6 mA (NAMUR NE43): wire break or failure-low signal
    STALE = "stale"  # the value stopped changing (stuck sensor / frozen device)
    NAN = "nan"  # the device reported NaN or the invalid-conversion code
    FAULT = "fault"  # the device flags an alarm / fault (status bits, alarm word, valve FAULT)
    SENSOR_FAULT = "sensor_fault"  # loop current outside NE43 3.8..20.5 mA (not open loop): no pressure

    @property
    def is_measurement(self) -> bool:
        """True if the value is a real reading (possibly a bound); False if it must not be used."""
        return self in (Quality.OK, Quality.OVER_RANGE, Quality.UNDER_RANGE)


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

REASONS = (
    "timeout", "silent", "disconnected", "bad_crc", "short_frame", "long_frame", "bad_header", "byte_count",
    "wrong_function", "wrong_unit", "wrong_transaction", "wrong_echo", "implausible", "exception", "fault", "reset",
    "trigger_not_started", "trigger_unknown", "profile", "error",
)


class DeviceError(Exception):
    """Base of every device-layer error; the message names the device and what failed.

    ``device``: the device's name (None if unknown); ``reason``: one word of REASONS.
    """

    reason = "error"

    def __init__(self, message: str = "", *, device: str | None = None, reason: str | None = None):
        super().__init__(message)
        self.device = device
        if reason is not None:
            self.reason = reason

    def again(self, message: str) -> "DeviceError":
        """The same error (class, device, reason, code) with another message."""
        new = self.__class__.__new__(self.__class__)
        Exception.__init__(new, message)
        new.__dict__.update(self.__dict__)
        return new


class DeviceTimeout(DeviceError):
    """The device did not answer within the configured timeout (after retries)."""

    reason = "timeout"


class StreamSilent(DeviceTimeout):
    """A streaming device sent no valid frame for ``data_s`` (silent, frozen, or only garbage)."""

    reason = "silent"


class DeviceDisconnected(DeviceError):
    """The transport is closed, refused, or the peer went away."""

    reason = "disconnected"


class ProtocolError(DeviceError):
    """A reply that cannot be trusted: it is never used. ``reason`` says why."""

    reason = "bad_header"


class ChecksumError(ProtocolError):
    """Bad CRC (Modbus RTU, streaming-ADC frame)."""

    reason = "bad_crc"


class FrameError(ProtocolError):
    """Frame shape: short / long frame, bad MBAP header, byte count not the one requested."""

    reason = "short_frame"


class ReplyMismatch(ProtocolError):
    """A well-formed reply that does not answer our request: function code, unit or transaction id."""

    reason = "wrong_function"


class ImplausibleReply(ProtocolError):
    """A well-formed reply whose content is impossible (unknown state code, counter backwards...)."""

    reason = "implausible"


class DeviceException(DeviceError):
    """The device answered with an error (a Modbus exception reply, an ``ERR`` line); ``code``."""

    reason = "exception"

    def __init__(self, message: str = "", code: int | None = None, *, device: str | None = None):
        super().__init__(message, device=device)
        self.code = code


class DeviceFault(DeviceError):
    """The device reports a fault state (e.g. the valve actuator's FAULT state or fault bits)."""

    reason = "fault"


class DeviceReset(DeviceError):
    """The device restarted under us: its sample counter went backwards; the stream is not continuous."""

    reason = "reset"


class TriggerNotStarted(DeviceError):
    """The valve did not start the manoeuvre (it refused, or a read-back after a lost reply says so).
    ``status``: the ValveStatus read back (None if the device refused outright)."""

    reason = "trigger_not_started"
    status = None


class TriggerRefused(TriggerNotStarted, DeviceException):
    """The valve answered TRIGGER with a Modbus exception (not ARMED, in FAULT): ``code``."""


class TriggerUnknown(DeviceError):
    """The TRIGGER reply was lost and the valve state could not be read back: it may be closing."""

    reason = "trigger_unknown"


class ProfileError(DeviceError, ConfigError):
    """A device profile (TOML) or bench table is invalid; the message names file and key."""

    reason = "profile"


# ----------------------------------------------------------------- calibration


@dataclass(frozen=True)
class LoopCalibration:
    """Linear analogue loop: signal (mA or V) -> engineering value.

    For a 4-20 mA pressure transducer over 0..6 bar: signal_lo=4, signal_hi=20,
    value_lo=0, value_hi=6e5 (Pa). ``zero_offset`` is subtracted from the value
    (transducer zero drift, found with the pipe at atmospheric pressure).
    ``fault_below`` / ``fault_above``: the NE43 measuring band of a current loop
    (3.8 / 20.5 mA); outside it the signal is a sensor fault, not a value.
    """

    signal_lo: float
    signal_hi: float
    value_lo: float
    value_hi: float
    units: str = "Pa"
    signal_units: str = "mA"
    zero_offset: float = 0.0
    open_loop_below: float | None = NE43_OPEN_LOOP_MA  # mA; None for voltage inputs
    range_margin: float = 0.0  # fraction of span tolerated beyond the ends before flagging
    fault_below: float | None = None  # default: NE43 3.8 mA for a 4-20 mA loop, else None
    fault_above: float | None = None  # default: NE43 20.5 mA for a 4-20 mA loop, else None

    def __post_init__(self):
        if self.signal_units == "mA" and self.signal_lo == 4.0 and self.signal_hi == 20.0:
            if self.fault_below is None:
                object.__setattr__(self, "fault_below", NE43_LOW_MA)
            if self.fault_above is None:
                object.__setattr__(self, "fault_above", NE43_HIGH_MA)

    def value(self, signal: float) -> float:
        frac = (signal - self.signal_lo) / (self.signal_hi - self.signal_lo)
        return self.value_lo + frac * (self.value_hi - self.value_lo) - self.zero_offset

    def signal(self, value: float) -> float:
        frac = (value + self.zero_offset - self.value_lo) / (self.value_hi - self.value_lo)
        return self.signal_lo + frac * (self.signal_hi - self.signal_lo)

    def quality(self, signal: float) -> Quality:
        """Quality of one signal value (see velab.drivers.blocks.signal_quality for arrays)."""
        if signal is None or (isinstance(signal, float) and math.isnan(signal)):
            return Quality.NAN
        if self.open_loop_below is not None and signal < self.open_loop_below:
            return Quality.OPEN_LOOP
        if (self.fault_below is not None and signal < self.fault_below) or \
                (self.fault_above is not None and signal > self.fault_above):
            return Quality.SENSOR_FAULT
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
