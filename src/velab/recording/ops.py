"""What the stages ask of the writer stage (velab.recording.writer): one small immutable message per
operation on the run file, dispatched by type (``WriterStage._APPLY``), never positional tuples."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Append:
    """Fast samples: the run's axis ``t`` and every fast channel (velab.recording.layout.FAST_CHANNELS)."""

    t: np.ndarray
    channels: dict


@dataclass(frozen=True)
class Event:
    """A line of the run's event log."""

    t: float
    kind: str
    text: str


@dataclass(frozen=True)
class Gap:
    """``lost`` samples missing before written sample ``sample``."""

    sample: int
    lost: int


@dataclass(frozen=True)
class Trigger:
    """The trigger instant on the run's axis (the estimate, then perhaps the measured one)."""

    t: float


@dataclass(frozen=True)
class Value:
    """One scalar of the run file (e.g. ``manoeuvre/trigger_host_time``)."""

    path: str
    value: Any


@dataclass(frozen=True)
class Slow:
    """A slow channel's sample (flow, valve state, valve opening)."""

    name: str
    t: float
    value: float
    epoch_s: float | None = None


@dataclass(frozen=True)
class Close:
    """The last operation: close the file with its status."""

    status: str
    reason: str


WriterOp = Append | Event | Gap | Trigger | Value | Slow | Close
