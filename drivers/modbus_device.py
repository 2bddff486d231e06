"""Base of the Modbus device drivers: a profile (register map) plus an injected RegisterBus."""

from __future__ import annotations

import time
from typing import Callable

from velab.drivers.base import DeviceError, Quality, Reading
from velab.drivers.modbus import RegisterBus
from velab.drivers.profile import Profile, RegisterSpec, load_profile


class RangeError(DeviceError, ValueError):
    """An argument is outside the range the device profile allows (nothing was sent)."""


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

    # -- raw register access through the profile
    def _read_regs(self, spec: RegisterSpec, count: int | None = None) -> list[int]:
        n = spec.count if count is None else count
        if spec.table == "input":
            return self.bus.read_input(spec.address, n, unit=self.unit)
        return self.bus.read_holding(spec.address, n, unit=self.unit)

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
        if isinstance(value, float) and value != value:
            quality = Quality.NAN
        elif spec.max is not None and value > spec.max:
            quality = Quality.OVER_RANGE
        elif spec.min is not None and value < spec.min:
            quality = Quality.UNDER_RANGE
        return Reading(float(value), spec.units, ts, quality, raw=regs[0] if len(regs) == 1 else None)

    def write_value(self, reg: str, value: float, what: str | None = None) -> None:
        spec = self.profile.reg(reg)
        if spec.access == "r":
            raise RangeError(f"{self.name}: register {reg!r} is read-only in {self.profile.path}")
        try:
            spec.check_range(value, what or reg)
        except ValueError as exc:
            raise RangeError(f"{self.name}: {exc}") from None
        self.bus.write_registers(spec.address, spec.to_registers(value), unit=self.unit)

    def close(self) -> None:
        self.bus.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
