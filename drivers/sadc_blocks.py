"""Streaming ADC: from parsed frames to SampleBlocks (gap accounting, conversion, quality).

The reader thread of velab.drivers.streaming_adc feeds frames in; blocks come out.
Nothing is invented: a gap in the device's sample counter is a new block with
``lost_before`` (exact), a reconnection restarts the counter (``restarted``, gap
estimated from host time), frames dropped by the parser (bad CRC, lost sync) are
counted in ``rejected_frames`` and their samples in ``lost_before``.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from velab.drivers.blocks import SampleBlock, StuckDetector, quality_limits, signal_quality, worst_quality
from velab.drivers.sadc_profile import ChannelProfile, StreamingADCProfile
from velab.drivers.sadc_protocol import (
    FLAG_INVALID,
    FLAG_OVERRUN,
    RAW_FULL_SCALE,
    RAW_INVALID,
    Frame,
    channel_mask,
    frame_length,
)


@dataclass
class StreamStats:
    samples: int = 0  # samples per channel delivered
    blocks: int = 0
    frames: int = 0
    lost: int = 0  # exact, from device sample-counter gaps (incl. the tail reported by STOP)
    lost_estimated: int = 0  # reconnection gaps, estimated from host time
    queue_dropped: int = 0  # samples dropped because the consumer's queue was full
    overruns: int = 0  # frames flagged OVERRUN by the device
    crc_errors: int = 0
    header_errors: int = 0
    resyncs: int = 0
    discarded_bytes: int = 0
    reconnects: int = 0
    stale_frames: int = 0  # CRC-valid frames whose counter went backwards (discarded)
    bytes_read: int = 0


@dataclass(frozen=True)
class AcquisitionConfig:
    rate_hz: float  # actual device rate (from the RATE reply)
    channels: tuple[ChannelProfile, ...]  # ascending input order
    block_samples: int

    @property
    def mask(self) -> int:
        return channel_mask(c.index for c in self.channels)

    @property
    def frame_len(self) -> int:
        return frame_length(len(self.channels), self.block_samples)


class BlockAssembler:
    """Frames of one acquisition (all its segments) -> SampleBlocks, with exact gap accounting."""

    def __init__(self, config: AcquisitionConfig, profile: StreamingADCProfile, stats: StreamStats,
                 stats_lock: threading.Lock):
        self.config = config
        self.profile = profile
        self.stats = stats
        self.lock = stats_lock
        self.segment = 0
        self.expected = 0  # first index of the next frame
        self.pending_lost = 0  # samples lost before the next block (reconnection estimate, queue drops)
        self.pending_restart = False
        self.pending_rejected = 0  # frames the parser rejected since the last block
        self._stuck = [StuckDetector(int(round(c.stuck_s * config.rate_hz)) if c.stuck_s else 0)
                       for c in config.channels]
        chans = config.channels
        cals = [c.calibration for c in chans]
        self._fs = np.array([c.full_scale for c in chans])
        self._s_lo = np.array([c.signal_lo for c in cals])
        self._s_hi = np.array([c.signal_hi for c in cals])
        self._v_lo = np.array([c.value_lo for c in cals])
        self._v_hi = np.array([c.value_hi for c in cals])
        self._zero = np.array([c.zero_offset for c in cals])
        self._limits = quality_limits(cals)

    def new_segment(self, estimated_lost: int) -> None:
        """The device was reconnected: its counter restarts at 0, the gap is an estimate."""
        self.segment += 1
        self.expected = 0
        self.pending_lost += estimated_lost
        self.pending_restart = True
        for d in self._stuck:
            d.reset()

    def frames(self, frames: list[Frame], host_t: float) -> list[SampleBlock]:
        k = self.config.block_samples
        run: list[Frame] = []
        run_lost = 0
        run_overrun = False
        lost_total = stale = overruns = 0
        blocks: list[SampleBlock] = []
        for f in frames:
            if f.first_index < self.expected:
                stale += 1  # counter went backwards: not ours to trust
                continue
            gap = f.first_index - self.expected
            if f.flags & FLAG_OVERRUN:
                overruns += 1
            if (gap or f.flags & FLAG_OVERRUN) and run:
                blocks.append(self._block(run, run_lost, run_overrun, host_t))
                run = []
            if not run:
                run_lost = gap
                run_overrun = bool(f.flags & FLAG_OVERRUN)
            lost_total += gap
            run.append(f)
            self.expected = f.first_index + k
        if run:
            blocks.append(self._block(run, run_lost, run_overrun, host_t))
        with self.lock:
            st = self.stats
            st.frames += len(frames) - stale
            st.stale_frames += stale
            st.lost += lost_total
            st.overruns += overruns
        return blocks

    @staticmethod
    def _worst(sq: np.ndarray) -> tuple:
        if not sq.any():  # the usual case: everything OK
            return (worst_quality(sq[:0, 0]),) * sq.shape[1]
        return tuple(worst_quality(sq[:, j]) for j in range(sq.shape[1]))

    def _block(self, run: list[Frame], lost: int, overrun: bool, host_t: float) -> SampleBlock:
        cfg = self.config
        chans = cfg.channels
        nch = len(chans)
        raw = np.frombuffer(b"".join(f.payload for f in run), dtype="<i2").reshape(-1, nch)
        flags = 0
        for f in run:
            flags |= f.flags
        invalid = raw == RAW_INVALID
        signal = raw * (self._fs / RAW_FULL_SCALE)
        if flags & FLAG_INVALID or invalid.any():
            signal[invalid] = np.nan
        values = self._v_lo + (signal - self._s_lo) / (self._s_hi - self._s_lo) * (self._v_hi - self._v_lo) - self._zero
        sq = signal_quality(signal, self._limits, invalid=invalid, clipped_hi=raw == RAW_FULL_SCALE,
                            clipped_lo=raw == -RAW_FULL_SCALE)
        for j, d in enumerate(self._stuck):
            if d.limit:
                d.flag(j, raw[:, j], sq[:, j])
        lost_before = lost + self.pending_lost
        rejected, restarted = self.pending_rejected, self.pending_restart
        self.pending_lost = self.pending_rejected = 0
        self.pending_restart = False
        return SampleBlock(
            segment=self.segment, first_index=run[0].first_index, rate_hz=cfg.rate_hz, host_time_s=host_t,
            raw=raw, signal=signal, values=values, channels=tuple(c.name for c in chans),
            units=tuple(c.calibration.units for c in chans), quality=self._worst(sq),
            lost_before=lost_before, restarted=restarted, overrun=overrun, flags=flags,
            density_kg_m3=self.profile.density_kg_m3, sample_quality=sq, rejected_frames=rejected,
        )
