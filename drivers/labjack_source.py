"""The LabJack's PressureSource (velab.drivers.pressure_source): ``LabJackT.pressure_source(name)`` makes it.

Like the streaming ADC's source (StreamingSource): the device pushes packets, the driver's reader thread turns
them into blocks; any error reaching the reader is fatal (the record is no longer continuous). The spot look
before a run is command-response (AIN# reads: the stream is not running then)."""

from __future__ import annotations

from dataclasses import asdict

import numpy as np

from velab.drivers.base import DeviceError, DeviceTimeout, pressure_to_head_m
from velab.drivers.identity import identity
from velab.drivers.pressure_source import READ_ERRORS, BlockRead, _acquired, _by_units

SPOT_READS = 5  # command-response reads averaged per channel for a spot look


class LabJackSource:
    def __init__(self, lj, name: str, clock_scale: float = 1.0):
        self.lj, self.name, self.clock_scale = lj, name, clock_scale
        self._rate = 0.0

    def channels(self) -> tuple[str | None, str | None]:
        chans = [(c.name, c.calibration.units) for c in self.lj.profile.channels]
        return _by_units(chans, [c[0] for c in chans])

    def pressure_channels(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.lj.profile.channels if c.calibration.units == "Pa")

    def rate_range(self) -> tuple[float, float]:
        """Scan rates for the pressure and the position channel (the model's sample rate over two)."""
        return 1.0, float(self.lj.profile.max_sample_rate_hz / 2)

    def calibration(self) -> dict:
        return {c.name: asdict(c.calibration) | {"ain": c.ain, "range_v": c.range, "shunt_ohm": c.shunt_ohm}
                for c in self.lj.profile.channels}

    def identity(self) -> dict:
        return identity(self.lj)

    def describe(self) -> str:
        i = self.lj.identify()
        return f"LabJack {i['model']} serial {i['serial']} firmware {i['firmware']} ({i['name']})"

    def spot_heads(self, rate_hz: float, channels: tuple[str, ...]) -> dict[str, tuple[float, str]]:
        out = {}
        for ch in channels:
            readings = [self.lj.read_analog(ch) for _ in range(SPOT_READS)]
            worst = max(readings, key=lambda r: r.quality is not r.quality.OK).quality
            mean = float(np.mean([r.value for r in readings]))
            head = pressure_to_head_m(mean, self.lj.density_kg_m3) if readings[0].units == "Pa" else mean
            out[ch] = (float(head), worst.value)
        return out

    def configure(self, rate_hz: float, pressure: tuple[str, ...] | None = None) -> float:
        self._rate = self.lj.configure(rate_hz, _acquired(self, pressure))
        return self._rate

    def start(self) -> float:
        self.lj.start()
        return self._rate

    def read_blocks(self, wait_s: float = 0.2) -> BlockRead:
        try:
            try:
                return BlockRead(tuple([self.lj.get_block(timeout=wait_s)] + self.lj.get_blocks()))
            except DeviceTimeout:
                if self.lj.error is not None:
                    raise self.lj.error from None
                return BlockRead()
        except READ_ERRORS as exc:
            raise DeviceError(str(exc), device=self.name) from None

    def stall_hint(self) -> str:
        return " (no stream packets: device silent or the network held them)" if self.lj.error is None else ""

    def stop(self) -> None:
        self.lj.stop()

