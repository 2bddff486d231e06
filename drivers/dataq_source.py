"""A DATAQ DAQ as velab's PressureSource (velab.drivers.pressure_source), made by ``DataqDAQ.pressure_source``.

The model followed is StreamingSource: the driver's reader thread queues blocks and every error reaching it is
fatal (it has reconnected already if it could).
"""

from __future__ import annotations

import time
from dataclasses import asdict

from velab.drivers.base import DeviceError, DeviceTimeout
from velab.drivers.identity import identity
from velab.drivers.pressure_source import READ_ERRORS, BlockRead, _acquired, _by_units, _look, sample_codes


class DataqSource:
    """PressureSource over a velab.drivers.dataq.DataqDAQ."""

    def __init__(self, daq, name: str, clock_scale: float = 1.0):
        self.daq, self.name, self.clock_scale = daq, name, clock_scale
        self._rate = 0.0

    def channels(self) -> tuple[str | None, str | None]:
        prof = self.daq.profile
        return _by_units([(c.name, c.calibration.units) for c in prof.channels], list(prof.enabled))

    def pressure_channels(self) -> tuple[str, ...]:
        first = self.channels()[0]
        rest = [c.name for c in sorted(self.daq.profile.channels, key=lambda c: c.input)
                if c.calibration.units == "Pa" and c.name != first]
        return tuple(([first] if first else []) + rest)

    def rate_range(self) -> tuple[float, float]:
        return self.daq.rate_range()

    def calibration(self) -> dict:
        return {c.name: asdict(c.calibration) | {"input": c.input, "shunt_ohm": c.shunt_ohm}
                for c in self.daq.profile.channels}

    def identity(self) -> dict:
        return identity(self.daq)

    def describe(self) -> str:
        i = self.daq.identify()
        return f"{i.get('manufacturer', '')} {i.get('model', '')} s/n {i.get('serial', '')} fw {i.get('firmware', '')}"

    def spot_heads(self, rate_hz: float, channels: tuple[str, ...]) -> dict[str, tuple[float, str]]:
        chans = list(channels)
        self.daq.configure(rate_hz, chans)
        self.daq.start()
        heads, codes = {c: [] for c in chans}, {c: [] for c in chans}
        try:
            need = max(10, int(0.05 * rate_hz))
            deadline = time.monotonic() + 5.0
            while sum(v.size for v in heads[chans[0]]) < need and time.monotonic() < deadline:
                b = self.daq.get_block(timeout=2.0)
                for c in chans:
                    heads[c].append(b.head_m(c))
                    codes[c].append(sample_codes(b, c))
        finally:
            self.daq.stop()
        return _look(heads, codes)

    def configure(self, rate_hz: float, pressure: tuple[str, ...] | None = None) -> float:
        self._rate = float(self.daq.configure(rate_hz, _acquired(self, pressure)))
        return self._rate  # exact: dividend / (srate x dec)

    def start(self) -> float:
        # back-pressure to the device: a consumer too slow for it ends in its own overflow report (stop 01)
        self.daq.start(wait_when_full=True)
        return self._rate

    def read_blocks(self, wait_s: float = 0.2) -> BlockRead:
        try:
            try:
                return BlockRead(tuple([self.daq.get_block(timeout=wait_s)] + self.daq.get_blocks()))
            except DeviceTimeout:
                if self.daq.error is not None:
                    raise self.daq.error from None
                return BlockRead()
        except READ_ERRORS as exc:
            raise DeviceError(str(exc)) from None

    def stall_hint(self) -> str:
        return " (device silent, stalled or reconnecting)" if self.daq.error is None else ""

    def stop(self) -> None:
        self.daq.stop()
