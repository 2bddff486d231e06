"""What one fit is: a :class:`FitRequest` (what to fit, the window, the user's choices: velab.fitting.options.FitOptions).

Immutable, typed and picklable: a request travels as it is to a thread, to the fit process
(velab.fit_worker) or to a Dask worker, and :func:`velab.fitservice.execute.execute` turns it into
the one call into the fitter. Building one never imports the fitter (scipy): the recorder and the
GUI make requests in processes that may never fit.

What to fit (``source``), one of:

* :class:`RunFile` -- a run file (``velab.fitting.entry.fit_run``, every section of its rig);
* :class:`RunFiles` -- two or more run files of one pipe, fitted jointly (``velab.fitting.joint.fit_joint``);
* :class:`Record` -- a recorded head record in memory, as the recorder holds it
  (``velab.fitting.entry.fit_record``).

The choices are the fitter's own FitOptions (light: no scipy), passed as they are to every entry point.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from velab.errors import DataError
from velab.fitting.options import FitOptions


# ------------------------------------------------------------------------------------------ sources
@dataclass(frozen=True)
class RunFile:
    """One run file. ``will_save``: the caller saves the fit into the run, so a run that cannot take
    it (open for writing, damaged) is refused before it is fitted (velab.fitservice.execute)."""

    path: str
    will_save: bool = False

    def __post_init__(self):
        object.__setattr__(self, "path", str(self.path))


@dataclass(frozen=True)
class RunFiles:
    """Two or more run files of one pipe, fitted jointly (one wall)."""

    paths: tuple[str, ...]

    def __post_init__(self):
        paths = tuple(str(p) for p in self.paths)
        if len(paths) < 2:
            raise DataError("a joint fit needs two or more runs")
        object.__setattr__(self, "paths", paths)


def _frozen(a) -> np.ndarray | None:
    if a is None:
        return None
    v = np.asarray(a).view()
    v.flags.writeable = False
    return v


@dataclass(frozen=True, eq=False)
class Record:
    """A head record in memory (the recorder's): ``t_s`` the run's time axis, ``head_m`` the absolute head
    of the valve's transducer there, ``position_pct`` the recorded valve position on ``t_s`` (or None),
    ``section_heads`` the other transducers' absolute heads by name (a rig with several). The arrays are
    held read-only."""

    t_s: np.ndarray
    head_m: np.ndarray
    trigger_time_s: float
    rig: Any  # velab.rig.Rig
    record_rate_hz: float
    position_pct: np.ndarray | None = None
    section_heads: tuple[tuple[str, np.ndarray], ...] = ()

    def __post_init__(self):
        for name in ("t_s", "head_m", "position_pct"):
            object.__setattr__(self, name, _frozen(getattr(self, name)))
        heads = self.section_heads.items() if isinstance(self.section_heads, dict) else self.section_heads
        object.__setattr__(self, "section_heads", tuple((str(k), _frozen(v)) for k, v in heads))
        if not (isinstance(self.record_rate_hz, (int, float)) and self.record_rate_hz > 0):
            raise DataError(f"sample rate must be positive, got {self.record_rate_hz!r} Hz")


# ------------------------------------------------------------------------------------------ the request
@dataclass(frozen=True, eq=False)
class FitRequest:
    """One fit: ``source`` (RunFile, RunFiles or Record), ``window_s`` after the trigger (None: the whole
    record), ``choices``; ``label`` names the fit in messages and thread names."""

    source: RunFile | RunFiles | Record
    window_s: float | None = 20.0
    choices: FitOptions = field(default_factory=FitOptions)
    label: str = ""

    def __post_init__(self):
        if not isinstance(self.source, (RunFile, RunFiles, Record)):
            raise DataError(f"nothing to fit: {type(self.source).__name__} is not a RunFile, RunFiles or Record")
        if not isinstance(self.choices, FitOptions):
            raise DataError(f"fit choices must be FitOptions, not {type(self.choices).__name__}")
        w = self.window_s
        if w is not None and not (isinstance(w, (int, float)) and math.isfinite(w) and w > 0):
            raise DataError(f"window {w!r}: seconds after the trigger, above 0 (None: the whole record)")

    @property
    def entry(self) -> str:
        """The fitting entry point this request calls (velab.fitting.entry, or fit_joint)."""
        if isinstance(self.source, RunFiles):
            return "joint"
        if isinstance(self.source, RunFile):
            return "run"
        return "record"


@dataclass(frozen=True)
class FitProgress:
    """A progress message of a running fit: ``done`` of ``total`` models, the last one fitted ``name``."""

    done: int
    total: int
    name: str
    label: str = ""
