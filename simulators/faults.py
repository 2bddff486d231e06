"""Fault injection for the simulated devices, from configuration or from tests.

Protocol-level faults of a Modbus device (``DeviceFaults``, one per served device)
act in the Modbus server (velab.simulators.modbus_server); the streaming ADC's are
its own (velab.simulators.streaming_adc.FaultPlan); model-level faults (sensors,
flowmeter, valve) live in ``velab.simulators.rig_faults``. A ``FaultPlan`` bundles
what a sim config's ``[faults]`` says::

    [faults.flowmeter]          # protocol faults of "flowmeter", from the start
    exception_code = 6          # every request answered with exception 6
    count = 3                   # ... only the next 3 requests (omit: until cleared)
    [faults.rig]                # model faults from the start (RigFaults)
    stuck_channels = { 0 = 1.5 }     # channel 0 stuck from t = 1.5 s

    [[faults.schedule]]         # a fault at an instant of the run (velab.simulators.schedule)
    device = "pressure_adc"
    fault = { silent = true }
    at = "trigger+1.5"
    duration_s = 0.5

Modbus protocol faults (``DeviceFaults`` fields = scheduled fault names):
delay_s (reply delayed; longer than the client's timeout = a timeout followed by a
late reply), exception_code, corrupt_crc (last byte flipped: a bad CRC on RTU),
garble (every byte XOR 0x5A), silent (no reply), short_by (reply truncated by N
bytes), extra_bytes (N junk bytes after the reply), wrong_unit (reply from another
unit id), disconnect (scheduled only: the endpoint goes away; comes back at the end
of the window, never without a duration), count (only the next N requests).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field, fields

from velab.errors import ConfigError
from velab.simulators.schedule import parse_schedule


@dataclass
class DeviceFaults:
    """Protocol faults of one simulated Modbus device, from the start; mutate at run time."""

    delay_s: float = 0.0
    exception_code: int | None = None
    corrupt_crc: bool = False
    garble: bool = False
    silent: bool = False
    short_by: int = 0
    extra_bytes: int = 0
    wrong_unit: bool = False
    count: int | None = None
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)

    def active(self) -> bool:
        return bool(self.delay_s or self.exception_code or self.corrupt_crc or self.garble or self.silent
                    or self.short_by or self.extra_bytes or self.wrong_unit)

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

    def as_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)
                if not f.name.startswith("_") and f.name != "count" and getattr(self, f.name)}

    def clear(self) -> None:
        self.delay_s, self.exception_code = 0.0, None
        self.corrupt_crc = self.garble = self.silent = self.wrong_unit = False
        self.short_by = self.extra_bytes = 0
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
    schedule: list = field(default_factory=list)  # the raw [[faults.schedule]] tables (checked by the bench)

    @classmethod
    def from_dict(cls, d: dict | None, where: str = "[faults]") -> "FaultPlan":
        d = dict(d or {})
        rig = d.pop("rig", {}) or {}
        schedule = d.pop("schedule", [])
        if not isinstance(rig, dict):
            raise ConfigError(f"{where}.rig: must be a table")
        unknown = sorted(set(rig) - _RIG_KEYS)
        if unknown:
            raise ConfigError(f"{where}.rig: unknown key {unknown[0]!r} (known: {', '.join(sorted(_RIG_KEYS))})")
        for key in ("stuck_channels", "channel_mA"):
            if key in rig:
                try:
                    rig[key] = {int(k): float(v) for k, v in rig[key].items()}
                except (AttributeError, TypeError, ValueError):
                    raise ConfigError(f"{where}.rig.{key}: must be a table {{channel = number}}") from None
        for name, faults in d.items():
            if not isinstance(faults, dict):
                raise ConfigError(f"{where}.{name}: must be a table of device faults")
            _validate_device_faults(faults, f"{where}.{name}")
        if not isinstance(schedule, list):
            raise ConfigError(f"{where}.schedule: must be an array of tables ([[faults.schedule]])")
        return cls(devices=d, rig=rig, schedule=schedule)

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

    def scheduled(self, devices: dict[str, str], where: str = "[faults]") -> list[dict]:
        """The checked schedule; ``devices`` maps names to kinds (plus "rig")."""
        return parse_schedule(self.schedule, devices, where)


def _validate_device_faults(faults: dict, where: str) -> None:
    """Modbus protocol faults, or the streaming ADC's (velab.simulators.streaming_adc.FaultPlan)."""
    try:
        DeviceFaults().set(**faults)
        return
    except ConfigError as exc:
        first = ConfigError(f"{where}: {exc}")
    try:
        from velab.simulators.streaming_adc import FaultPlan as StreamFaults
    except ImportError:
        raise first from None
    try:
        StreamFaults().set(**faults)
    except (ValueError, TypeError):
        raise first from None
