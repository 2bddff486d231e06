"""One ``SampleBlock`` for every sampled-data driver (streaming ADC, buffered Modbus ADC).

The recorder has one code path for "a block of pressure samples": whatever the
device, a block is a contiguous run of samples (no gap inside) of all acquired
channels, with raw counts, signals (mA/V), engineering values and their quality,
the device's sample counter, and how many samples were lost just before it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from velab.drivers.base import Quality, pressure_to_head_m

# per-sample quality codes (``SampleBlock.sample_quality``) index into this tuple
QUALITY_CODES = (Quality.OK, Quality.OVER_RANGE, Quality.UNDER_RANGE, Quality.OPEN_LOOP, Quality.NAN, Quality.FAULT,
                 Quality.STALE)
QUALITY_CODE = {q: i for i, q in enumerate(QUALITY_CODES)}
_SEVERITY = (Quality.FAULT, Quality.NAN, Quality.OPEN_LOOP, Quality.OVER_RANGE, Quality.UNDER_RANGE, Quality.STALE)


def worst_quality(codes: np.ndarray) -> Quality:
    """The most severe quality among per-sample codes (OK if there are none)."""
    present = {QUALITY_CODES[int(c)] for c in np.unique(codes)} if np.size(codes) else set()
    for q in _SEVERITY:
        if q in present:
            return q
    return Quality.OK


@dataclass(frozen=True, eq=False)
class SampleBlock:
    """A contiguous run of samples (no gap inside), all channels.

    Row ``i`` was sampled at device time ``device_t0_s + (first_index + i) / rate_hz``
    (the device's sample clock; ``first_index`` counts samples since the START of
    stream ``segment``). ``host_time_s`` is the host epoch time (``time.time()``)
    associated with the block's last sample (for a stream: when its last byte was
    read). ``lost_before`` samples per channel are missing between the previous
    block and this one: exact from the device counter, except in the first block
    after a reconnection (``restarted``), where the counter restarted and the gap
    is estimated from host time. Missing samples are never filled in.
    """

    segment: int
    first_index: int
    rate_hz: float
    host_time_s: float
    raw: np.ndarray  # (n, ch) ADC counts (int16 for the streaming ADC, uint16 for Modbus)
    signal: np.ndarray  # (n, ch) mA or V; NaN where the conversion is invalid
    values: np.ndarray  # (n, ch) engineering units
    channels: tuple[str, ...]
    units: tuple[str, ...]
    quality: tuple[Quality, ...]  # per channel, worst over the block
    lost_before: int = 0
    restarted: bool = False
    overrun: bool = False
    flags: int = 0  # device-specific flag bits (streaming ADC: OR of the frames' flags)
    density_kg_m3: float = 998.2
    sample_quality: np.ndarray | None = None  # (n, ch) uint8 codes into QUALITY_CODES, if per-sample
    device_t0_s: float = 0.0  # device time of sample index 0

    # ---- sizes and axes
    @property
    def n(self) -> int:
        return self.raw.shape[0]

    def __len__(self) -> int:
        return self.raw.shape[0]

    @property
    def fs_hz(self) -> float:
        return self.rate_hz

    @property
    def channel_names(self) -> tuple[str, ...]:
        return self.channels

    @property
    def index(self) -> np.ndarray:
        return self.first_index + np.arange(self.n)

    @property
    def next_index(self) -> int:
        return self.first_index + self.n

    @property
    def t0_s(self) -> float:
        return self.device_t0_s + self.first_index / self.rate_hz

    @property
    def device_time_s(self) -> np.ndarray:
        return self.device_t0_s + (self.first_index + np.arange(self.n)) / self.rate_hz

    @property
    def host_times_s(self) -> np.ndarray:
        """Host epoch time of every sample, from the last sample's host time and the device rate."""
        return self.host_time_s - (self.n - 1 - np.arange(self.n)) / self.rate_hz

    # ---- values
    def column(self, channel: str) -> np.ndarray:
        return self.values[:, self.channels.index(channel)]

    def raw_column(self, channel: str) -> np.ndarray:
        return self.raw[:, self.channels.index(channel)]

    def head_m(self, channel: str = "pressure") -> np.ndarray:
        """Pressure head (m of water) of a channel whose values are in Pa."""
        i = self.channels.index(channel)
        if self.units[i] != "Pa":
            raise ValueError(f"channel {channel!r} is in {self.units[i]}, not Pa")
        return pressure_to_head_m(self.values[:, i], self.density_kg_m3)

    def quality_of(self, i: int, ch: int = 0) -> Quality:
        """Quality of sample ``i`` of channel ``ch`` (the block's worst if not per-sample)."""
        if self.sample_quality is not None:
            return QUALITY_CODES[int(self.sample_quality[i, ch])]
        return self.quality[ch]
