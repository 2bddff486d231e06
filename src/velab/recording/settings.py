"""RecordSettings: everything an operator sets for one run, validated, stored whole in the run file."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

from velab.errors import VelabError

DEFAULT_ARMED_TIMEOUT_S = 300.0  # an armed rig left without a trigger disarms itself after this


def _finite(name: str, v, lo: float | None = None, hi: float | None = None, *, strict_lo: bool = False) -> None:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise VelabError(f"{name} must be a finite number, got {v!r}")
    if lo is not None and (v <= lo if strict_lo else v < lo):
        raise VelabError(f"{name} must be {'>' if strict_lo else '>='} {lo:g}, got {v!r}")
    if hi is not None and v > hi:
        raise VelabError(f"{name} must be at most {hi:g}, got {v!r}")


@dataclass(frozen=True)
class RecordSettings:
    """One run's settings; the whole object goes into ``/entry/notes@settings_json``."""

    duration_s: float = 30.0  # recorded after the trigger
    pretrigger_s: float = 2.0  # baseline before the trigger
    sample_rate_hz: float = 1000.0  # pressure source rate
    beta_per_s: float | None = None  # None -> the rig's manoeuvre
    gamma: float | None = None
    end_position_pct: float = 0.0
    out_dir: Path = Path("runs")
    title: str = ""
    operator: str = ""
    specimen: str = ""
    notes: str = ""
    fit: bool = True
    fit_models: tuple = (0, 1, 2, 3, 4, 5, 6)
    fit_window_s: float = 20.0
    fit_method: str = "auto"
    online_fit: bool = True  # fit as soon as the window is in (and publish intermediate fits)
    surge_margin: float = 0.1  # fraction added to the Joukowsky surge
    ceiling_head_m: float | None = None  # None -> 95 % of the limiting pressure, as head
    flow_tolerance: float = 0.05  # steady flow within this fraction of the rig's Q0, and stable
    flush_interval_s: float = 0.25
    intermediate_fits: bool = True
    # the online fits run in a worker process of their own (velab.fit_worker), started at the trigger;
    # False: in the recorder's process (same result, but it takes turns with the recorder's threads)
    fit_process: bool = True
    run_number: int = 1
    head_range: tuple = (0.5, 1.5)  # steady head accepted as this range x the rig's steady head
    # bounds on waiting (engine); per-sample quality (stuck counts, NE43 limits) is the drivers', from their profiles
    armed_timeout_s: float | None = None  # None -> the bench's [recorder] armed_timeout_s, else 300 s
    stall_timeout_s: float = 3.0  # wall seconds without pressure samples -> the run fails

    def __post_init__(self):
        object.__setattr__(self, "out_dir", Path(self.out_dir))
        try:
            object.__setattr__(self, "fit_models", tuple(int(m) for m in self.fit_models))
            object.__setattr__(self, "head_range", tuple(float(x) for x in self.head_range))
        except (TypeError, ValueError):
            raise VelabError(f"fit_models and head_range must be numbers, got {self.fit_models!r}, "
                             f"{self.head_range!r}") from None
        for name in ("duration_s", "sample_rate_hz", "fit_window_s", "flush_interval_s",
                     "stall_timeout_s"):
            _finite(name, getattr(self, name), 0.0, strict_lo=True)
        _finite("pretrigger_s", self.pretrigger_s, 0.05)
        _finite("end_position_pct", self.end_position_pct, 0.0)
        if self.end_position_pct >= 100.0:
            raise VelabError(f"end_position_pct must be in [0, 100), got {self.end_position_pct!r}")
        _finite("surge_margin", self.surge_margin, 0.0)
        _finite("flow_tolerance", self.flow_tolerance, 0.0, strict_lo=True)
        for name in ("beta_per_s", "gamma", "ceiling_head_m"):
            v = getattr(self, name)
            if v is not None:
                _finite(name, v)
        if self.beta_per_s is not None and self.beta_per_s <= 0:
            raise VelabError(f"beta_per_s must be positive, got {self.beta_per_s!r}")
        if self.ceiling_head_m is not None and self.ceiling_head_m <= 0:
            raise VelabError(f"ceiling_head_m must be positive, got {self.ceiling_head_m!r}")
        if self.armed_timeout_s is not None:
            _finite("armed_timeout_s", self.armed_timeout_s, self.pretrigger_s + 0.5, 24 * 3600.0)
        if self.flush_interval_s > 0.5:
            raise VelabError("flush_interval_s must be at most 0.5 s (crash safety)")
        if len(self.head_range) != 2 or not 0 <= self.head_range[0] < self.head_range[1]:
            raise VelabError(f"head_range must be (low, high) with 0 <= low < high, got {self.head_range!r}")
        if not self.fit_models or any(not 0 <= m <= 6 for m in self.fit_models):
            raise VelabError(f"fit_models must be model orders 0..6, got {self.fit_models!r}")
        if self.fit and self.fit_window_s > self.duration_s + 1e-9:
            raise VelabError(f"fit window {self.fit_window_s:g} s is longer than the record after the trigger "
                             f"({self.duration_s:g} s): lengthen --duration or shorten --window")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["out_dir"] = str(self.out_dir)
        d["fit_models"] = list(self.fit_models)
        d["head_range"] = list(self.head_range)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "RecordSettings":
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise VelabError(f"unknown record setting {unknown[0]!r}")
        return cls(**d)

    def with_changes(self, **kw) -> "RecordSettings":
        return replace(self, **kw)

    def armed_timeout(self, bench_value: float | None = None) -> float:
        """The armed timeout in force: this run's setting, else the bench's, else the default."""
        if self.armed_timeout_s is not None:
            return float(self.armed_timeout_s)
        if bench_value is not None:
            return float(bench_value)
        return max(DEFAULT_ARMED_TIMEOUT_S, self.pretrigger_s + 1.0)
