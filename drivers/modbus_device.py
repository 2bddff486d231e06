"""Base of the Modbus device drivers: a profile (register map) plus an injected RegisterBus.

Every bus call goes through ``_read_regs`` / ``_write_regs`` so that an error
escaping a driver names the driver's device (``exc.device = self.name``).
Register contents are checked where the device has a physical range: a value
outside the profile's [min, max] is flagged (OVER/UNDER_RANGE), NaN is NAN, and
an impossible content (an unknown state code) is an ``ImplausibleReply`` after
one re-read.
"""

from __future__ import annotations

import math
import time
from typing import Callable

from velab.drivers.base import DeviceError, ImplausibleReply, Quality, Reading
from velab.drivers.modbus import RegisterBus
from velab.drivers.profile import Profile, RegisterSpec, load_profile


class RangeError(DeviceError, ValueError):
    """An argument is outside the range the device profile allows (nothing was sent)."""

    reason = "range"


class ModbusDevice:
    """One Modbus device: ``bus`` (any RegisterBus) + ``profile`` (name, path or Profile).

    ``unit`` defaults to the profile's ``default_unit``; ``word_order`` overrides the
    profile's default word order; ``clock`` gives reading timestamps (time.time).
    """

    kind = "modbus"
    default_profile = ""

    def __init__(self, bus: RegisterBus, profile: Profile | str | None = None, *, unit: int | None = None,
                 word_order: str | None = None, name: str | None = None,
                 clock: Callable[[], float] = time.time):
        self.bus = bus
        self.profile = load_profile(profile or self.default_profile)
        if word_order:
            self.profile = self.profile.with_word_order(word_order)
        self.unit = self.profile.default_unit if unit is None else unit
        self.name = name or self.kind
        self.clock = clock

    # -- bus access: errors name this device
    def _named(self, exc: DeviceError) -> DeviceError:
        exc.device = self.name
        return exc

    def _bus_read(self, table: str, address: int, count: int) -> list[int]:
        try:
            if table == "input":
                return self.bus.read_input(address, count, unit=self.unit)
            return self.bus.read_holding(address, count, unit=self.unit)
        except DeviceError as exc:
            raise self._named(exc)

    def _write_regs(self, address: int, values: list[int], retries: int | None = None) -> None:
        try:
            if retries is None:
                self.bus.write_registers(address, values, unit=self.unit)
            else:
                self.bus.write_registers(address, values, unit=self.unit, retries=retries)
        except DeviceError as exc:
            raise self._named(exc)

    def _read_regs(self, spec: RegisterSpec, count: int | None = None) -> list[int]:
        return self._bus_read(spec.table, spec.address, spec.count if count is None else count)

    def _implausible(self, what: str) -> ImplausibleReply:
        return ImplausibleReply(f"{self.name}: {what}", device=self.name)

    def _reread_once(self, read: Callable):
        """``read()`` again once if its reply was implausible (a glitch gets one more chance)."""
        try:
            return read()
        except ImplausibleReply:
            return read()

    # -- registers through the profile
    def read_value(self, reg: str) -> float | int:
        spec = self.profile.reg(reg)
        return spec.to_value(self._read_regs(spec))

    def read(self, reg: str) -> Reading:
        """One register as a Reading (engineering units, host timestamp, quality from its range)."""
        spec = self.profile.reg(reg)
        regs = self._read_regs(spec)
        return self._reading(spec, regs, self.clock())

    def _reading(self, spec: RegisterSpec, regs: list[int], ts: float) -> Reading:
        value = spec.to_value(regs)
        quality = Quality.OK
        if isinstance(value, float) and math.isnan(value):
            quality = Quality.NAN
        elif spec.max is not None and value > spec.max:
            quality = Quality.OVER_RANGE
        elif spec.min is not None and value < spec.min:
            quality = Quality.UNDER_RANGE
        return Reading(float(value), spec.units, ts, quality, raw=regs[0] if len(regs) == 1 else None)

    def write_value(self, reg: str, value: float, what: str | None = None) -> None:
        spec = self.profile.reg(reg)
        if spec.access == "r":
            raise RangeError(f"{self.name}: register {reg!r} is read-only in {self.profile.path}", device=self.name)
        try:
            spec.check_range(value, what or reg)
        except ValueError as exc:
            raise RangeError(f"{self.name}: {exc}", device=self.name) from None
        self._write_regs(spec.address, spec.to_registers(value))

    def close(self) -> None:
        self.bus.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
