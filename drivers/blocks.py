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

# per-sample quality codes (``SampleBlock.sample_quality``, uint8) index into this tuple;
# the codes are stored in run files: append new ones, never renumber.
QUALITY_CODES = (Quality.OK, Quality.OVER_RANGE, Quality.UNDER_RANGE, Quality.OPEN_LOOP, Quality.NAN, Quality.FAULT,
                 Quality.STALE, Quality.SENSOR_FAULT)
QUALITY_CODE = {q: i for i, q in enumerate(QUALITY_CODES)}
_SEVERITY = (Quality.FAULT, Quality.OPEN_LOOP, Quality.SENSOR_FAULT, Quality.NAN, Quality.STALE, Quality.OVER_RANGE,
             Quality.UNDER_RANGE)
# codes whose value is a measurement (OK, or a bound beyond the calibrated span)
MEASUREMENT_CODES = tuple(QUALITY_CODE[q] for q in QUALITY_CODES if q.is_measurement)


def worst_quality(codes: np.ndarray) -> Quality:
    """The most severe quality among per-sample codes (OK if there are none)."""
    present = {QUALITY_CODES[int(c)] for c in np.unique(codes)} if np.size(codes) else set()
    for q in _SEVERITY:
        if q in present:
            return q
    return Quality.OK


def quality_limits(cals) -> np.ndarray:
    """(5, ch) thresholds of loop calibrations: open loop, NE43 fault low / high, span under / over
    (+-inf where a check does not apply), for ``signal_quality``."""
    inf = np.inf
    rows = []
    for c in cals:
        span = c.signal_hi - c.signal_lo
        rows.append((-inf if c.open_loop_below is None else c.open_loop_below,
                     -inf if c.fault_below is None else c.fault_below,
                     inf if c.fault_above is None else c.fault_above,
                     c.signal_lo - c.range_margin * span, c.signal_hi + c.range_margin * span))
    return np.array(rows, dtype=float).T


_C_OVER, _C_UNDER = QUALITY_CODE[Quality.OVER_RANGE], QUALITY_CODE[Quality.UNDER_RANGE]
_C_FAULT, _C_OPEN, _C_NAN = QUALITY_CODE[Quality.SENSOR_FAULT], QUALITY_CODE[Quality.OPEN_LOOP], QUALITY_CODE[Quality.NAN]


def signal_quality(signal: np.ndarray, cal, *, invalid: np.ndarray | None = None,
                   clipped_hi: np.ndarray | None = None, clipped_lo: np.ndarray | None = None) -> np.ndarray:
    """Per-sample quality codes (uint8) of signals (mA or V), by precedence:
    NAN (invalid / NaN) > OPEN_LOOP (< 3.6 mA) > SENSOR_FAULT (outside NE43 3.8..20.5 mA)
    > OVER_RANGE / UNDER_RANGE (beyond the calibrated span by more than range_margin, or the
    ADC clipped at that end) > OK. ``signal`` is (n,) with one LoopCalibration, or (n, ch) with
    ``cal`` = the (5, ch) array of ``quality_limits``. One function for every sampled-data driver."""
    s = np.asarray(signal, dtype=float)
    lim = cal if isinstance(cal, np.ndarray) else quality_limits([cal])[:, 0]
    q = np.zeros(s.shape, dtype=np.uint8)
    with np.errstate(invalid="ignore"):
        under = s < lim[3]
        over = s > lim[4]
        if clipped_lo is not None:
            under |= clipped_lo
        if clipped_hi is not None:
            over |= clipped_hi
        q[under] = _C_UNDER
        q[over] = _C_OVER
        q[(s < lim[1]) | (s > lim[2])] = _C_FAULT
        q[s < lim[0]] = _C_OPEN
    bad = np.isnan(s)
    if invalid is not None:
        bad |= invalid
    q[bad] = _C_NAN
    return q


class StuckDetector:
    """Flags runs of identical raw counts longer than ``limit`` samples (across blocks) as STALE.

    A live transducer's noise moves the last bits of a 16-bit ADC at every sample: a channel
    that repeats the same count for longer than ``limit`` samples is a stuck sensor or a frozen
    converter. Only samples still OK are re-flagged (a worse code is kept).
    """

    def __init__(self, limit: int):
        self.limit = int(limit)
        self._run: dict[int, tuple[int, int]] = {}  # channel -> (raw value, run length)

    def flag(self, ch: int, raw: np.ndarray, q: np.ndarray) -> None:
        if raw.size == 0 or self.limit <= 0:
            return
        prev_val, prev_len = self._run.get(ch, (None, 0))
        change = np.flatnonzero(np.diff(raw.astype(np.int64))) + 1
        starts = np.concatenate([[0], change])
        lengths = np.diff(np.concatenate([starts, [raw.size]]))
        carried = np.zeros(starts.size, dtype=np.int64)
        if raw[0] == prev_val:
            carried[0] = prev_len  # the first run continues the previous block's last run
        total = carried + lengths
        for i in np.flatnonzero(total > self.limit):  # only the (rare) long runs: a Python loop is fine
            a, b = int(starts[i]), int(starts[i] + lengths[i])
            first = max(a, a + self.limit - int(carried[i]))
            seg = q[first:b]
            seg[seg == 0] = QUALITY_CODE[Quality.STALE]
        self._run[ch] = (int(raw[-1]), int(total[-1]))

    def reset(self) -> None:
        self._run.clear()


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
    ``rejected_frames``: frames thrown away since the previous block (bad CRC, bad
    header, lost sync); their samples are part of ``lost_before``.
    ``sample_quality`` (n, ch) uint8 codes into QUALITY_CODES, always set by velab's
    drivers; ``quality`` is the worst per channel.
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
    rejected_frames: int = 0  # corrupted / unsynchronised frames dropped just before this block

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
        return self.host_times_at(self.rate_hz)

    def host_times_at(self, host_rate_hz: float) -> np.ndarray:
        """Host epoch time of every sample, the samples ``host_rate_hz`` apart in host time: the device rate at a
        bench, the rate times the clock scale on a simulated rig's fast clock (its samples come that much faster)."""
        return self.host_time_s - (self.n - 1 - np.arange(self.n)) / host_rate_hz

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

    def good(self, channel: str | int = 0) -> np.ndarray:
        """Boolean mask of the samples of a channel that are measurements (OK / over / under range)."""
        ch = channel if isinstance(channel, int) else self.channels.index(channel)
        if self.sample_quality is None:
            return np.full(self.n, self.quality[ch].is_measurement)
        return np.isin(self.sample_quality[:, ch], MEASUREMENT_CODES)

    def quality_of(self, i: int, ch: int = 0) -> Quality:
        """Quality of sample ``i`` of channel ``ch`` (the block's worst if not per-sample)."""
        if self.sample_quality is not None:
            return QUALITY_CODES[int(self.sample_quality[i, ch])]
        return self.quality[ch]
