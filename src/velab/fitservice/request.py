"""What one fit is: a :class:`FitRequest` (what to fit, the window, the user's :class:`FitChoices`).

Immutable, typed and picklable: a request travels as it is to a thread, to the fit process
(velab.fit_worker) or to a Dask worker, and :func:`velab.fitservice.execute.execute` turns it into
the one call into the fitter. Building one never imports the fitter (scipy): the recorder and the
GUI make requests in processes that may never fit.

What to fit (``source``), one of:

* :class:`RunFile` -- a run file (``velab.fitting.prepare.fit_run``, every section of its rig);
* :class:`RunFiles` -- two or more run files of one pipe, fitted jointly (``velab.fitting.joint.fit_joint``);
* :class:`Record` -- a recorded head record in memory, as the recorder holds it
  (``velab.fitting.prepare.fit_record``, or ``fit_lead`` with ``stage="lead"``).

:meth:`FitChoices.to_kwargs` is the one place where the user's choices become the keyword arguments
of today's fitting entry points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from velab.errors import DataError

SELECTIONS = ("ar1", "white")  # velab.fitting.results.SELECTIONS (named here: no fitter import)
STEADY_LAWS = ("quadratic", "linear", "none")  # velab.friction's laws
UNSTEADY_LAWS = ("none", "vardy-brown", "brunone")
MANOEUVRES = ("auto", "fitted", "rig")  # velab.fitting.manoeuvre's sources of the flow at the valve
ENTRIES = ("record", "run", "lead", "joint")
STAGES = ("fit", "lead")

# options a joint fit does not take (it has its own search), and the command-line option that names each
_NOT_JOINT = {"reduced": "--reduced", "starts": "--starts", "polish": "--no-polish"}


@dataclass(frozen=True)
class FitChoices:
    """The user's choices for one fit, as ``velab fit`` names them (docs/fitting.md).

    ``models``: a model list ("0-6", "1,3": checked by the fitter, a bad one is DataError) or model
    numbers (0 = EL); ``method`` the search method; ``reduced`` also S1r..S5r; ``starts`` a cap on the
    starts per model (None: all); ``polish`` the full-band polish; ``tau_min_s``/``tau_max_s`` the
    retardation-time bounds; ``selection`` "ar1" or "white"; ``friction``/``friction_unsteady``
    override the rig's laws; ``manoeuvre`` the flow at the valve ("auto", "fitted", "rig").
    Bad values raise DataError (one line) here."""

    models: str | tuple[int, ...] = (0, 1, 2, 3, 4, 5, 6)
    method: str = "auto"
    reduced: bool = False
    starts: int | None = None
    polish: bool = True
    tau_min_s: float | None = None
    tau_max_s: float | None = None
    selection: str = "ar1"
    friction: str | None = None
    friction_unsteady: str | None = None
    manoeuvre: str = "auto"

    def __post_init__(self):
        if not isinstance(self.models, str):
            try:
                object.__setattr__(self, "models", tuple(int(m) for m in self.models))
            except (TypeError, ValueError):
                raise DataError(f"bad model list {self.models!r}: model numbers 0..6 (0 = EL)") from None
        if not isinstance(self.method, str) or not self.method:
            raise DataError(f"bad search method {self.method!r}")
        if self.starts is not None and (isinstance(self.starts, bool) or not isinstance(self.starts, int)
                                        or self.starts < 1):
            raise DataError(f"starts {self.starts!r}: a whole number of at least 1 (None: all)")
        for name in ("tau_min_s", "tau_max_s"):
            v = getattr(self, name)
            if v is not None and not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise DataError(f"{name} {v!r}: a retardation time in seconds, above 0")
        if self.tau_min_s is not None and self.tau_max_s is not None and not self.tau_min_s < self.tau_max_s:
            raise DataError(f"tau_min_s {self.tau_min_s:g} must be below tau_max_s {self.tau_max_s:g}")
        for name, allowed in (("selection", SELECTIONS), ("manoeuvre", MANOEUVRES)):
            if getattr(self, name) not in allowed:
                raise DataError(f"{name} {getattr(self, name)!r}: choose from {', '.join(allowed)}")
        for name, allowed in (("friction", STEADY_LAWS), ("friction_unsteady", UNSTEADY_LAWS)):
            v = getattr(self, name)
            if v is not None and v not in allowed:
                raise DataError(f"{name} {v!r}: choose from {', '.join(allowed)} (None: the rig's)")

    def to_kwargs(self, entry: str = "record") -> dict[str, Any]:
        """The keyword arguments of the fitting entry point ``entry`` for these choices: "record"
        (fit_record), "run" (fit_run), "lead" (fit_lead) or "joint" (fit_joint). ``models`` and (but for
        a joint fit) ``method`` are always given, every other choice only where it is not the fitter's
        default: the recorder's online fit and ``velab fit`` of its file then make the same call, and
        the lead fit's key (velab.fitting.lead.options_key) is the final fit's. A joint fit refuses the
        single fit's search options (DataError naming the ``velab fit`` option)."""
        if entry not in ENTRIES:
            raise ValueError(f"unknown fitting entry point {entry!r} (one of {', '.join(ENTRIES)})")
        models = self.models
        if isinstance(models, str):
            from velab.fitting.sweep import parse_models  # the fitter's own check of a model list

            models = parse_models(models)
        kw: dict[str, Any] = {"models": list(models)}
        defaults = {f.name: f.default for f in fields(self)}
        if entry == "joint":
            for name, option in _NOT_JOINT.items():
                if getattr(self, name) != defaults[name]:
                    raise DataError(f"{option} does not apply to a joint fit (--joint)")
            if self.method != "auto":
                raise DataError(f"--method {self.method}: a joint fit has its own search (--joint takes the default)")
        else:
            kw["method"] = self.method
        for name in ("reduced", "starts", "polish", "tau_min_s", "tau_max_s", "selection", "friction",
                     "friction_unsteady", "manoeuvre"):
            v = getattr(self, name)
            if v != defaults[name]:
                kw[name] = v
        return kw


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
    record), ``choices``. For a Record only: ``stage`` "lead" is the lead fit of a ``window_s`` fit
    (velab.fitting.lead; its result is None when that window has none), and ``lead`` is what the fit
    continues from (a lead SweepResult; True: computed in this fit; False: one step). ``label`` names
    the fit in messages and thread names."""

    source: RunFile | RunFiles | Record
    window_s: float | None = 20.0
    choices: FitChoices = field(default_factory=FitChoices)
    stage: str = "fit"
    lead: Any = True
    label: str = ""

    def __post_init__(self):
        if not isinstance(self.source, (RunFile, RunFiles, Record)):
            raise DataError(f"nothing to fit: {type(self.source).__name__} is not a RunFile, RunFiles or Record")
        if not isinstance(self.choices, FitChoices):
            raise DataError(f"fit choices must be FitChoices, not {type(self.choices).__name__}")
        w = self.window_s
        if w is not None and not (isinstance(w, (int, float)) and math.isfinite(w) and w > 0):
            raise DataError(f"window {w!r}: seconds after the trigger, above 0 (None: the whole record)")
        if self.stage not in STAGES:
            raise DataError(f"stage {self.stage!r}: one of {', '.join(STAGES)}")
        if self.stage == "lead" and (not isinstance(self.source, Record) or w is None):
            raise DataError("a lead fit is of a recorded Record, for a given window")

    @property
    def entry(self) -> str:
        """The fitting entry point this request calls (FitChoices.to_kwargs)."""
        if isinstance(self.source, RunFiles):
            return "joint"
        if isinstance(self.source, RunFile):
            return "run"
        return "lead" if self.stage == "lead" else "record"


@dataclass(frozen=True)
class FitProgress:
    """A progress message of a running fit: ``done`` of ``total`` models, the last one fitted ``name``."""

    done: int
    total: int
    name: str
    label: str = ""
