"""Helpers for testing the recorder's stages alone (tests/recording, tests/drivers): synthetic sample
blocks and a hooks object that records what a stage reports. No sockets, no simulated rig."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np

from velab.drivers.base import Quality, head_to_pressure_pa
from velab.drivers.blocks import SampleBlock
from velab.recording.types import Hooks

CHANNELS = ("pressure", "valve_position")


def block(first: int, n: int, *, rate_hz: float = 1000.0, head_m=30.0, position_pct=100.0, codes=None,
          lost_before: int = 0, restarted: bool = False, host_time_s: float | None = None,
          others: dict | None = None) -> SampleBlock:
    """``n`` samples from device index ``first``: pressure (Pa, from ``head_m``: a number or an array) and
    valve position (%), then more pressure channels (``others``: channel name -> head, a number or an array:
    the transducers of several sections); per-sample quality ``codes`` (n, channels) uint8 (default all ok)."""
    others = others or {}
    heads = [np.broadcast_to(np.asarray(h, dtype=float), (n,)) for h in [head_m, *others.values()]]
    pos = np.broadcast_to(np.asarray(position_pct, dtype=float), (n,))
    values = np.column_stack([head_to_pressure_pa(heads[0]), pos] + [head_to_pressure_pa(h) for h in heads[1:]])
    raw = np.round(values).astype(np.int32)
    k = values.shape[1]
    sq = np.zeros((n, k), np.uint8) if codes is None else np.asarray(codes, np.uint8)
    return SampleBlock(segment=0, first_index=first, rate_hz=rate_hz,
                       host_time_s=(first + n) / rate_hz if host_time_s is None else host_time_s,
                       raw=raw, signal=values.copy(), values=values, channels=CHANNELS + tuple(others),
                       units=("Pa", "%") + ("Pa",) * len(others), quality=(Quality.OK,) * k,
                       lost_before=lost_before, restarted=restarted, sample_quality=sq)


def codes_of(b: SampleBlock) -> dict:
    """The per-sample quality codes of every channel of a block, by name (what the pressure stage hands on)."""
    return {ch: b.sample_quality[:, j] for j, ch in enumerate(b.channels)}


@dataclass
class RecordingHooks:
    """The stages' Hooks, recording every call (thread-safe); ``hooks`` is what a stage takes."""

    emitted: list = field(default_factory=list)
    logged: list = field(default_factory=list)
    faults: list = field(default_factory=list)
    ends: list = field(default_factory=list)
    ended: threading.Event = field(default_factory=threading.Event)

    @property
    def hooks(self) -> Hooks:
        return Hooks(emit=lambda kind, data: self.emitted.append((kind, data)),
                     log=lambda kind, text: self.logged.append((kind, text)),
                     fault=lambda who, message, kind="error", **x: self.faults.append((who, message, kind, x)),
                     request_end=self._end)

    def _end(self, status: str, reason: str) -> None:
        self.ends.append((status, reason))
        self.ended.set()

    def kinds(self, kind: str) -> list:
        return [d for k, d in self.emitted if k == kind]
