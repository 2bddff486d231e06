"""What a user chooses for a fit: ``FitOptions``, checked at the door, the same for every kind of fit.

A single record, a record's several sections and a campaign of runs take one ``FitOptions``; what the fit
derives from the record (the flow at the valve, the steady head's prior, the closure's marginalisation) is not a
choice and is not here.

    FitOptions(models=(1, 2, 3), selection="white")      # frozen; FitOptions.of(**choices) from keywords
    opts.replace(window_s=8.0)

Light on purpose (no scipy): the recorder, the GUI and the command line build and check options without
loading the fitter.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace

from velab.errors import DataError
from velab.friction import STEADY_LAWS, UNSTEADY_LAWS

MAX_M = 6  # the largest model, S6
METHODS = ("auto", "least-squares", "nelder-mead", "evolution")
SELECTIONS = ("ar1", "white")  # velab.fitting.selection: the AR(1) likelihood's AIC (default), the paper's
MANOEUVRES = ("auto", "fitted", "rig")  # velab.fitting.manoeuvre.valve_input's modes


def parse_models(spec) -> list[int]:
    """'0-6', '1,3,5', '3', 'S3,EL' or an iterable of ints -> the sorted list of m in 0..6 (0 = EL)."""
    if isinstance(spec, str):
        out: set[int] = set()
        for part in spec.replace(" ", "").split(","):
            if not part:
                continue
            try:
                if "-" in part:
                    a, b = part.split("-", 1)
                    lo, hi = int(a), int(b)
                    if not 0 <= lo <= hi <= MAX_M:  # before range(): "0-10**12" must not build a huge set
                        raise DataError(f"bad model list {spec!r}: ranges must be within 0..{MAX_M} (0 = EL)")
                    out.update(range(lo, hi + 1))
                else:
                    out.add(int(part.upper().lstrip("S").replace("EL", "0") or 0))
            except ValueError:
                raise DataError(f"bad model list {spec!r}: use e.g. 0-6 or 1,3,5 (0 = EL)") from None
        ms = sorted(out)
    else:
        try:
            ms = sorted(set(int(v) for v in spec))
        except (TypeError, ValueError):
            raise DataError(f"bad model list {spec!r}: use e.g. 0-6 or 1,3,5 (0 = EL)") from None
    if not ms or ms[0] < 0 or ms[-1] > MAX_M:
        raise DataError(f"bad model list {spec!r}: m must be within 0..{MAX_M} (0 = EL)")
    return ms


def _one_of(name: str, value, allowed: tuple) -> None:
    if value not in allowed:
        raise DataError(f"unknown {name} {value!r} (choose from {', '.join(allowed)})")


def _positive_or_none(name: str, value) -> float | None:
    if value is None:
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise DataError(f"{name} must be a number of seconds, got {value!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise DataError(f"{name} must be a positive number of seconds, got {value!r}")
    return v


@dataclass(frozen=True)
class FitOptions:
    """A fit's choices. ``models``: m of each model (0 = EL); ``window_s``: seconds after the trigger (None:
    the whole record); ``method``: the coarse search (METHODS); ``reduced``: also S1r..S5r (tau fixed);
    ``polish``: the full-band polish; ``starts``: at most this many coarse starts a model (None: all);
    ``seed``: of the evolution method; ``tau_min_s`` / ``tau_max_s``: the retardation-time box (None: the rig's
    ``[fit]`` table, else from the data); ``threads``: 1 or 2 (None: two on a machine that has them; the
    result is the same); ``selection``: the criterion (SELECTIONS); ``friction`` / ``friction_unsteady``: the
    rig's laws overridden (None: the rig's); ``manoeuvre``: the flow at the valve (MANOEUVRES: "auto" takes
    the recorded position if there is one, else fits the closure; "fitted"; "rig": the rig's sigmoid).

    Every value is checked when made: DataError, one line naming the option."""

    models: tuple[int, ...] = tuple(range(MAX_M + 1))
    window_s: float | None = 20.0
    method: str = "auto"
    reduced: bool = False
    polish: bool = True
    starts: int | None = None
    seed: int = 0
    tau_min_s: float | None = None
    tau_max_s: float | None = None
    threads: int | None = None
    selection: str = "ar1"
    friction: str | None = None
    friction_unsteady: str | None = None
    manoeuvre: str = "auto"

    def __post_init__(self):
        set_ = object.__setattr__  # (frozen: the checked, normalised values)
        set_(self, "models", tuple(parse_models(self.models)))
        set_(self, "window_s", _positive_or_none("the fit window", self.window_s))
        _one_of("fit method", self.method, METHODS)
        _one_of("model selection", self.selection, SELECTIONS)
        _one_of("manoeuvre input", self.manoeuvre, MANOEUVRES)
        if self.friction is not None:
            _one_of("friction law", self.friction, STEADY_LAWS)
        if self.friction_unsteady is not None:
            _one_of("unsteady friction law", self.friction_unsteady, UNSTEADY_LAWS)
        if self.starts is not None and (isinstance(self.starts, bool) or not isinstance(self.starts, int)
                                        or self.starts < 1):
            raise DataError(f"starts must be a whole number of at least 1 (or None: all), got {self.starts!r}")
        if self.threads is not None and self.threads not in (1, 2):
            raise DataError(f"threads must be 1 or 2 (or None), got {self.threads!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int):
            raise DataError(f"seed must be a whole number, got {self.seed!r}")
        set_(self, "reduced", bool(self.reduced))
        set_(self, "polish", bool(self.polish))
        lo = _positive_or_none("tau_min_s", self.tau_min_s)
        hi = _positive_or_none("tau_max_s", self.tau_max_s)
        if lo is not None and hi is not None and not lo < hi:
            raise DataError(f"tau_min_s {lo:g} s must be below tau_max_s {hi:g} s")
        set_(self, "tau_min_s", lo)
        set_(self, "tau_max_s", hi)

    @classmethod
    def of(cls, options: "FitOptions | None" = None, **choices) -> "FitOptions":
        """``options`` (default: the defaults) with ``choices`` by name; an unknown name is one line."""
        base = options if options is not None else cls()
        unknown = sorted(set(choices) - NAMES)
        if unknown:
            raise DataError(f"unknown fit option{'s' if len(unknown) > 1 else ''} {', '.join(unknown)} "
                            f"(choose from {', '.join(sorted(NAMES))})")
        return replace(base, **choices) if choices else base

    def replace(self, **choices) -> "FitOptions":
        return FitOptions.of(self, **choices)

    @property
    def default_search(self) -> bool:
        """The default search: method "auto", the polish, every start."""
        return self.method == "auto" and self.polish and self.starts is None

    def key(self) -> str:
        """What a fit was made with, as a string: every choice but ``threads`` (which does not change the
        result)."""
        d = asdict(self)
        d.pop("threads")
        return repr(sorted(d.items()))

    def to_dict(self) -> dict:
        d = asdict(self)
        d["models"] = list(self.models)
        return d


NAMES = frozenset(f.name for f in fields(FitOptions))
# (every option is every fit's: the stacked sweep, velab.fitting.joint, takes each of them as the single sweep does,
# the reduced models too -- issue 51)
