"""One pressure-source interface over both pressure ADCs, in the ophyd-async manner: one verb set,
the device's own verbs chosen once, when the source is made (``pressure_source(driver)``).

    src = pressure_source(driver, "adc", clock_scale=1.0)
    src.channels()                 # (pressure channel, valve-position channel or None), by units
    src.pressure_channels()        # every channel in Pa (the transducers it can record: several sections)
    src.rate_range(); src.calibration(); src.identity()
    looks = src.spot_heads(rate_hz, ("pressure",))  # a short look before anything is armed: {channel: (head, quality)}
    rate = src.configure(rate_hz, pressure=("pressure", "pressure_2"))  # channels (default: the first); the rate it will run at
    rate = src.start()                           # the rate the device reports once it runs
    r = src.read_blocks()          # BlockRead: blocks (each with per-sample quality), or a transient error
    src.stop()

The streaming ADC (``configure/start/get_block/stop``) pushes frames from its own reader thread:
any error is fatal (it has reconnected already if it could). The buffered Modbus ADC
(``configure_buffer/start_buffer/read_buffer/stop_buffer``) is polled: a failed poll is transient,
its ring keeps the samples, the next poll reads them. ``read_blocks`` waits at most ``wait_s``.
Every block holds the valve-position channel (if the source has one) and the pressure channels asked
for (the buffered ADC records its inputs 0..n-1: the spares between them come along, unused).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from typing import Protocol

import numpy as np

from velab.drivers.base import DeviceError, DeviceTimeout, pressure_to_head_m
from velab.drivers.blocks import QUALITY_CODE, SampleBlock, worst_quality
from velab.drivers.identity import identity
from velab.drivers.modbus_adc import ModbusADC
from velab.drivers.sadc_protocol import MAX_BLOCK, RATE_MAX_HZ, RATE_MIN_HZ, auto_block
from velab.drivers.streaming_adc import StreamingADC

READ_ERRORS = (DeviceError, ValueError, IndexError)  # what a device call raises for a bad device or reply
POLL_S = 0.01  # a polled source's pause between empty reads


@dataclass(frozen=True)
class BlockRead:
    """One read: the blocks that arrived (maybe none), or the transient error of a polled source
    (``error``; ``note`` says why it is transient)."""

    blocks: tuple[SampleBlock, ...] = ()
    error: str = ""
    note: str = ""


class PressureSource(Protocol):
    name: str

    def channels(self) -> tuple[str, str | None]: ...
    def pressure_channels(self) -> tuple[str, ...]: ...
    def rate_range(self) -> tuple[float, float]: ...
    def calibration(self) -> dict: ...
    def identity(self) -> dict: ...
    def describe(self) -> str: ...
    def spot_heads(self, rate_hz: float, channels: tuple[str, ...]) -> dict[str, tuple[float, str]]: ...
    def configure(self, rate_hz: float, pressure: tuple[str, ...] | None = None) -> float: ...
    def start(self) -> float: ...
    def read_blocks(self, wait_s: float = 0.2) -> BlockRead: ...
    def stall_hint(self) -> str: ...
    def stop(self) -> None: ...


def pressure_source(driver, name: str, clock_scale: float = 1.0) -> PressureSource:
    """The pressure-source interface of ``driver``: a StreamingADC, a ModbusADC, or any driver that makes its
    own (``driver.pressure_source(name, clock_scale)``: the DAQ families' drivers)."""
    own = getattr(driver, "pressure_source", None)
    if callable(own):
        return own(name, clock_scale)
    if isinstance(driver, StreamingADC):
        return StreamingSource(driver, name, clock_scale)
    if isinstance(driver, ModbusADC):
        return BufferedSource(driver, name)
    raise DeviceError(f"{name}: a {type(driver).__name__} is not a pressure source", device=name)


def sample_codes(b: SampleBlock, channel: str) -> np.ndarray:
    """The driver's per-sample quality codes of one channel (a driver that gives only a worst
    quality per block: that, for every sample)."""
    j = b.channels.index(channel)
    if b.sample_quality is not None:
        return b.sample_quality[:, j]
    return np.full(b.n, QUALITY_CODE[b.quality[j]], np.uint8)


def _by_units(chans: list[tuple[str, str]], enabled: list[str]) -> tuple[str | None, str | None]:
    p = next((n for n, u in chans if u == "Pa" and n in enabled), None)
    v = next((n for n, u in chans if u == "%" and n in enabled), None)
    return p, v


def _acquired(source, pressure: tuple[str, ...] | None) -> list[str]:
    """The channels a run acquires: the pressure channels asked for (default: the first), then the position's."""
    p, v = source.channels()
    chans = list(pressure) if pressure else [p]
    for ch in chans:
        if ch not in source.pressure_channels():
            raise DeviceError(f"{source.name}: {ch!r} is not a pressure channel (units Pa) "
                              f"(have: {', '.join(source.pressure_channels())})", device=source.name)
    return chans + ([v] if v and v not in chans else [])


def _look(heads: dict, codes: dict) -> dict[str, tuple[float, str]]:
    """Per channel: the mean head of the samples looked at and their worst quality."""
    out = {}
    for ch, vals in heads.items():
        h = np.concatenate(vals) if vals else np.array([np.nan])
        q = worst_quality(np.concatenate(codes[ch])).value if codes[ch] else "ok"
        out[ch] = (float(np.nanmean(h)) if np.isfinite(h).any() else float("nan")), q
    return out


class StreamingSource:
    """The streaming ADC: its reader thread queues blocks; every error reaching the reader is fatal."""

    def __init__(self, adc: StreamingADC, name: str, clock_scale: float = 1.0):
        self.adc, self.name, self.clock_scale = adc, name, clock_scale
        self._rate = 0.0

    def channels(self) -> tuple[str | None, str | None]:
        prof = self.adc.profile
        return _by_units([(c.name, c.calibration.units) for c in prof.channels], list(prof.enabled))

    def pressure_channels(self) -> tuple[str, ...]:
        """Every input in Pa of the profile (acquired or not by default), the default pressure channel first."""
        first = self.channels()[0]
        rest = [c.name for c in sorted(self.adc.profile.channels, key=lambda c: c.index)
                if c.calibration.units == "Pa" and c.name != first]
        return tuple(([first] if first else []) + rest)

    def rate_range(self) -> tuple[float, float]:
        return float(RATE_MIN_HZ), float(RATE_MAX_HZ)

    def calibration(self) -> dict:
        return {c.name: asdict(c.calibration) | {"range": c.range, "input": c.index} for c in self.adc.profile.channels}

    def identity(self) -> dict:
        return identity(self.adc)

    def describe(self) -> str:
        return self.adc.identify()

    def _block_samples(self, fs: float, n_channels: int = 2) -> int:
        # frames for ~200/s of device time: a fast simulated clock gets bigger frames, not more of them
        n = max(1, n_channels)
        return int(min(MAX_BLOCK, max(auto_block(fs, n), auto_block(fs * self.clock_scale, n))))

    def spot_heads(self, rate_hz: float, channels: tuple[str, ...]) -> dict[str, tuple[float, str]]:
        chans = list(channels)
        self.adc.configure(rate_hz, chans, self._block_samples(rate_hz, len(chans)))
        self.adc.start()
        heads, codes = {c: [] for c in chans}, {c: [] for c in chans}
        try:
            need = max(10, int(0.05 * rate_hz))
            deadline = time.monotonic() + 5.0
            while sum(v.size for v in heads[chans[0]]) < need and time.monotonic() < deadline:
                b = self.adc.get_block(timeout=2.0)
                for c in chans:
                    heads[c].append(b.head_m(c))
                    codes[c].append(sample_codes(b, c))
        finally:
            self.adc.stop()
        return _look(heads, codes)

    def configure(self, rate_hz: float, pressure: tuple[str, ...] | None = None) -> float:
        chans = _acquired(self, pressure)
        cfg = self.adc.configure(rate_hz, chans, self._block_samples(rate_hz, len(chans)))
        self._rate = float(cfg.rate_hz) if abs(cfg.rate_hz - rate_hz) > 1e-6 * rate_hz else float(rate_hz)
        return self._rate  # the clock divider's rate

    def start(self) -> float:
        # back-pressure to the device: its FIFO overrun is then counted exactly from its sample counter
        self.adc.start(wait_when_full=True)
        return self._rate

    def read_blocks(self, wait_s: float = 0.2) -> BlockRead:
        try:
            try:
                return BlockRead(tuple([self.adc.get_block(timeout=wait_s)] + self.adc.get_blocks()))
            except DeviceTimeout:
                if self.adc.error is not None:  # the reader gave up: fatal
                    raise self.adc.error from None
                return BlockRead()
        except READ_ERRORS as exc:
            raise DeviceError(str(exc)) from None

    def stall_hint(self) -> str:
        return " (device silent, frozen or reconnecting)" if self.adc.error is None else ""

    def stop(self) -> None:
        self.adc.stop()


class BufferedSource:
    """The buffered Modbus ADC: polled; a failed poll is transient (its ring keeps the samples)."""

    NOTE = "retrying; the module's buffer keeps the samples"

    def __init__(self, adc: ModbusADC, name: str):
        self.adc, self.name = adc, name
        self._rate = 0.0

    def channels(self) -> tuple[str | None, str | None]:
        chans = [(c.name, c.calibration.units) for c in self.adc.channels]
        return _by_units(chans, [c[0] for c in chans])

    def pressure_channels(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.adc.channels if c.calibration.units == "Pa")

    def rate_range(self) -> tuple[float, float]:
        spec = self.adc.profile.reg("sample_rate")
        return float(spec.min if spec.min is not None else 1.0), float(spec.max if spec.max is not None else 1e4)

    def calibration(self) -> dict:
        return {c.name: asdict(c.calibration) | {"type_code": c.type_code, "input": c.index} for c in self.adc.channels}

    def identity(self) -> dict:
        return identity(self.adc)

    def describe(self) -> str:
        return ", ".join(f"{k} {v.value:.4g} {v.units}" for k, v in self.adc.read_channels().items())

    def spot_heads(self, rate_hz: float, channels: tuple[str, ...]) -> dict[str, tuple[float, str]]:
        readings = self.adc.read_channels()  # one polled read: every input at one instant
        return {c: (float(pressure_to_head_m(readings[c].value, self.adc.density_kg_m3)), readings[c].quality.value)
                for c in channels}

    def configure(self, rate_hz: float, pressure: tuple[str, ...] | None = None) -> float:
        # the module records its inputs 0..n-1: n reaches the highest input acquired
        n = max(self.adc.channel(c).index for c in _acquired(self, pressure)) + 1
        self.adc.stop_buffer()
        hz = int(round(rate_hz))  # its rate register holds whole hertz; start() reads back what it runs at
        self.adc.configure_buffer(hz, n)
        self._rate = float(hz)
        return self._rate

    def start(self) -> float:
        self.adc.start_buffer()  # the module's rate is known once it runs
        return float(self.adc.sample_rate_hz or self._rate)

    def read_blocks(self, wait_s: float = 0.2) -> BlockRead:
        try:
            b = self.adc.read_buffer()
        except READ_ERRORS as exc:
            time.sleep(POLL_S)  # (a device that fails fast is not polled in a tight loop)
            return BlockRead(error=str(exc), note=self.NOTE)
        if b.n or b.lost_before:
            return BlockRead((b,))
        time.sleep(POLL_S)  # nothing new yet: the module fills its ring at the sample rate
        return BlockRead()

    def stall_hint(self) -> str:
        return ""

    def stop(self) -> None:
        self.adc.stop_buffer()
