"""Fault injection for the simulated devices, from configuration or from tests.

Protocol-level faults (``DeviceFaults``, one per served device) act in the Modbus
server: reply delay (timeouts), Modbus exception replies, corrupted CRC / garbled
bytes, a silent device, and disconnect/reconnect (``ModbusDeviceServer.disconnect``).
Model-level faults (stuck sensor, out of range, NaN, valve fault during the
manoeuvre) live in ``velab.simulators.rig.RigFaults``. A ``FaultPlan`` bundles both,
as read from the ``[faults]`` tables of a sim config::

    [faults.flowmeter]          # protocol faults of the device named "flowmeter"
    exception_code = 6          # every request answered with exception 6
    count = 3                   # ... only the next 3 requests (omit: until cleared)
    [faults.rig]
    flow_nan = true
    stuck_channels = { 0 = 1.5 }     # channel 0 stuck from t = 1.5 s
    channel_mA = { 1 = 22.0 }
    valve_fault_after_s = 0.08
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field, fields

from velab.errors import ConfigError


@dataclass
class DeviceFaults:
    """Protocol faults of one simulated device; mutate at run time (thread-safe enough: plain attributes).

    delay_s : every reply is delayed this long (longer than the client timeout = a timeout)
    exception_code : answer every request with this Modbus exception code
    corrupt_crc : flip the last byte of every reply (RTU: bad CRC; TCP: wrong data/byte)
    garble : replace replies with junk bytes of the same length
    silent : send no reply at all
    count : apply the fault to only the next ``count`` requests (None = until cleared)
    """

    delay_s: float = 0.0
    exception_code: int | None = None
    corrupt_crc: bool = False
    garble: bool = False
    silent: bool = False
    count: int | None = None
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)

    def active(self) -> bool:
        return bool(self.delay_s or self.exception_code or self.corrupt_crc or self.garble or self.silent)

    def consume(self) -> bool:
        """Called once per request: True if the fault applies to this one."""
        with self._lock:
            if not self.active():
                return False
            if self.count is None:
                return True
            if self.count <= 0:
                return False
            self.count -= 1
            return True

    def clear(self) -> None:
        self.delay_s, self.exception_code = 0.0, None
        self.corrupt_crc = self.garble = self.silent = False
        self.count = None

    def set(self, **kw) -> "DeviceFaults":
        names = {f.name for f in fields(self) if not f.name.startswith("_")}
        for k, v in kw.items():
            if k not in names:
                raise ConfigError(f"unknown device fault {k!r} (known: {', '.join(sorted(names))})")
            setattr(self, k, v)
        return self


_RIG_KEYS = {"stuck_channels", "channel_mA", "flow_nan", "flow_value", "flow_stuck_at",
             "flow_alarm_bits", "valve_fault_after_s", "valve_fault_bits"}


@dataclass
class FaultPlan:
    devices: dict = field(default_factory=dict)  # device name -> dict of DeviceFaults fields
    rig: dict = field(default_factory=dict)  # RigFaults fields

    @classmethod
    def from_dict(cls, d: dict | None, where: str = "[faults]") -> "FaultPlan":
        d = dict(d or {})
        rig = d.pop("rig", {}) or {}
        unknown = sorted(set(rig) - _RIG_KEYS)
        if unknown:
            raise ConfigError(f"{where}.rig: unknown key {unknown[0]!r} (known: {', '.join(sorted(_RIG_KEYS))})")
        for key in ("stuck_channels", "channel_mA"):
            if key in rig:
                rig[key] = {int(k): float(v) for k, v in rig[key].items()}
        for name, faults in d.items():
            if not isinstance(faults, dict):
                raise ConfigError(f"{where}.{name}: must be a table of device faults")
            _validate_device_faults(faults)
        return cls(devices=d, rig=rig)

    def apply(self, rig_sim, device_faults: dict) -> None:
        for k, v in self.rig.items():
            setattr(rig_sim.faults, k, v)
        for name, kw in self.devices.items():
            if name not in device_faults:
                raise ConfigError(f"[faults.{name}]: no such simulated device (have: {', '.join(device_faults)})")
            try:
                device_faults[name].set(**kw)
            except ValueError as exc:  # another kind's fault names (the streaming ADC's FaultPlan)
                raise ConfigError(f"[faults.{name}]: {exc}") from None


def _validate_device_faults(faults: dict) -> None:
    """Modbus protocol faults, or the streaming ADC's (velab.simulators.streaming_adc.FaultPlan)."""
    try:
        DeviceFaults().set(**faults)
        return
    except ConfigError as exc:
        first = exc
    try:
        from velab.simulators.streaming_adc import FaultPlan as StreamFaults
    except ImportError:
        raise first from None
    try:
        StreamFaults().set(**faults)
    except (ValueError, TypeError):
        raise first from None
