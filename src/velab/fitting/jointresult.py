"""The result of a joint fit (velab.fitting.joint): a SweepResult over several runs, and its runs' table."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from velab.fitting.results import SweepResult

JOINT_KIND = "joint"  # the fit group's velab_fit_kind attribute (velab.runfiles.fits.save_fit)


@dataclass
class JointResult(SweepResult):
    """A SweepResult over several runs: ``runs`` per run (path, hash, n, noise ratio, disagrees,
    its own wall under the best model, ...)."""

    runs: list = field(default_factory=list)

    def to_dict(self) -> dict:
        d = super().to_dict()
        d["joint"] = True
        d["runs"] = [dict(r) for r in self.runs]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "JointResult":
        base = SweepResult.from_dict(d)
        return cls(**{f: getattr(base, f) for f in SweepResult.__dataclass_fields__}, runs=list(d.get("runs") or []))


def runs_report(result: JointResult) -> str:
    """The text table of a joint fit's runs: each run's n, Q0, F/noise under the joint wall, the steady head
    offset its model took from its baseline's mean (velab.fitting.offset), its own wave speed under the best
    model, how its flow at the valve was obtained, and whether it disagrees; under a run with several
    transducers, each section's n, F/noise, misfit bound and offset."""
    lines = [f"runs (each under the joint {result.best.name} wall; offset: its steady head's from the baseline's "
             f"mean; own a: the wall fitted on that run alone):",
             f"  {'run':<32}{'n':>7}{'Q0 (l/s)':>10}{'F/noise':>9}{'bound':>7}{'offset (mm)':>12}  {'own a (m/s)':>18}"
             f"  {'flow at valve':<15}disagrees"]
    for r in result.runs:
        own = r.get("own") or {}
        ratio, bound = r.get("noise_ratio"), r.get("misfit_bound")
        a, se = own.get("wave_speed", math.nan), own.get("wave_speed_se", math.nan)
        lines.append(f"  {str(r.get('path', '?'))[-32:]:<32}{int(r.get('n', 0)):>7}"
                     f"{1e3 * float(r.get('steady_flow_m3_s', math.nan)):>10.3g}"
                     f"{ratio if ratio is not None else math.nan:>9.3g}{bound if bound is not None else math.nan:>7.3g}"
                     f"{_mm(r.get('steady_head_offset')):>12}  {a:>9.2f} +- {se:<6.2g}"
                     f"  {_valve(r.get('manoeuvre')):<15}{'YES' if r.get('disagrees') else 'no'}")
        for sec in r.get("sections") or ():  # a run with several transducers: each section under the joint wall
            ratio, bound = sec.get("noise_ratio"), sec.get("misfit_bound")
            where = f"section {sec.get('name', '?')} at {float(sec.get('position_m', math.nan)):g} m"
            lines.append(f"    {where:<30}{int(sec.get('n', 0)):>7}{'':>10}"
                         f"{ratio if ratio is not None else math.nan:>9.3g}{bound if bound is not None else math.nan:>7.3g}"
                         f"{_mm(sec.get('steady_head_offset')):>12}{'':>37}"
                         f"{'YES' if sec.get('disagrees') else 'no'}")
    return "\n".join(lines)


def _valve(manoeuvre) -> str:
    """How a run's flow at the valve was obtained, in a word or two: its recorded position, a closure fitted with
    the shape of the valve its rig describes ("rig's shape") or with its own ("fitted shape"), the rig's sigmoid."""
    m = manoeuvre or {}
    if m.get("source") == "fitted":
        return "rig's shape" if m.get("shape") == "rig" else "fitted shape"
    return {"position": "position", "rig": "rig sigmoid"}.get(m.get("source"), "-")


def _mm(offset_m) -> str:
    """A steady head offset (m) in mm, "-" for a fit stored before offsets were fitted."""
    return "-" if offset_m is None else f"{1e3 * float(offset_m):+.3g}"
