"""What a fit was made with and what it derived: ``FitSettings``, the result's typed, frozen settings.

One record of every key a fit stores (its JSON ``settings`` object, the run file's fit group): the user's
choices (FitOptions' values), what the sweep derived (decimation, the retardation-time box, the
models not searched), the flow at the valve (``manoeuvre``), the record's preparation (``record``), and what a
joint or sections fit adds. A field never set is absent from ``to_dict`` (the JSON of every kind of fit is
what it was before the settings were typed); a key this version does not know, read from a newer document,
is kept in ``extra`` and written back as it was.

Read as a mapping too (``settings["manoeuvre"]``, ``settings.get("lead")``): the JSON's view, for readers of
stored documents and older code. It is never changed in place: ``replace(**fields)`` gives a new one.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace as _replace


class _Unset:
    """The value of a field that was never set (absent from the JSON)."""

    _instance = None

    def __new__(cls):
        if cls._instance is None:
            cls._instance = super().__new__(cls)
        return cls._instance

    def __repr__(self) -> str:
        return "UNSET"

    def __bool__(self) -> bool:
        return False

    def __reduce__(self):  # (pickled to the fit worker and back: the one instance)
        return (_Unset, ())


UNSET = _Unset()


@dataclass(frozen=True, eq=False)
class FitSettings(Mapping):
    """The settings of a fit (module docstring). Fields in the JSON's order; UNSET: not part of this fit."""

    # the user's choices and what the sweep derived, in the order a single fit's JSON has them
    models: object = UNSET  # [m, ...]
    reduced: object = UNSET
    polish: object = UNSET
    starts: object = UNSET
    seed: object = UNSET
    decimation: object = UNSET  # the coarse grid's step
    coarse_band_hz: object = UNSET
    tau_start_range_s: object = UNSET
    tau_min_s: object = UNSET
    tau_max_s: object = UNSET
    bounds: object = UNSET  # velab.fitting.params.FitBounds.to_dict()
    selection: object = UNSET
    warm_start: object = UNSET
    lead: object = UNSET  # {"window_s", "best", "evaluations", "duration_s", "computed_in_this_fit"} or None
    as_in_lead: object = UNSET
    not_searched: object = UNSET
    friction: object = UNSET  # {"steady", "unsteady", "time_domain", ...}
    time_domain_polish: object = UNSET
    # what the fit path adds: the flow at the valve, the record's preparation
    manoeuvre: object = UNSET  # velab.fitting.manoeuvre.ValveInput.describe()
    manoeuvre_refined: object = UNSET  # (a lead fit of an earlier version: its refined closure)
    record: object = UNSET  # velab.fitting.prepare.PreparedRecord.describe()
    lead_for: object = UNSET  # (a lead fit of an earlier version: what it was made for)
    window_s_requested: object = UNSET  # the window asked for (None: the whole record)
    # a stacked fit (several sections, several runs: velab.fitting.joint)
    method: object = UNSET  # its coarse search (options.METHODS; the result's method is "joint"/"sections")
    joint: object = UNSET
    sections: object = UNSET
    not_continued: object = UNSET
    k_shared: object = UNSET
    k_nuisance: object = UNSET
    likelihood: object = UNSET
    # keys of a newer document, kept as they were
    extra: dict = field(default_factory=dict)

    @classmethod
    def from_dict(cls, d) -> "FitSettings":
        """From a settings object (a stored fit's JSON, or a dict a fit made); unknown keys go to ``extra``."""
        if isinstance(d, FitSettings):
            return d
        d = dict(d or {})
        known = {k: d.pop(k) for k in list(d) if k in _FIELDS}
        return cls(**known, extra=d)

    def replace(self, **changes) -> "FitSettings":
        """A copy with ``changes`` (field names; another name is a TypeError)."""
        bad = sorted(set(changes) - set(_FIELDS))
        if bad:
            raise TypeError(f"FitSettings has no field {', '.join(bad)}")
        return _replace(self, **changes)

    def to_dict(self) -> dict:
        """The JSON object: every field that was set, then ``extra``."""
        out = {name: getattr(self, name) for name in _FIELDS if getattr(self, name) is not UNSET}
        out.update(self.extra)
        return out

    # ---------------------------------------------------------------- the mapping view (the JSON's keys)
    def __getitem__(self, key: str):
        if key in _FIELDS:
            value = getattr(self, key)
            if value is UNSET:
                raise KeyError(key)
            return value
        return self.extra[key]

    def __iter__(self):
        return iter(self.to_dict())

    def __len__(self) -> int:
        return len(self.to_dict())

    def __eq__(self, other) -> bool:
        if isinstance(other, (FitSettings, Mapping)):
            return self.to_dict() == dict(other)
        return NotImplemented

    def __repr__(self) -> str:
        return f"FitSettings({self.to_dict()!r})"


_FIELDS = tuple(f.name for f in fields(FitSettings) if f.name != "extra")
