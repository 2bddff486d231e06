"""The runs of a campaign as a joint fit takes them (velab.fitting.joint): one run's record and identity,
and the check that the runs are of one pipe."""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field

import numpy as np

from velab.rig import Rig
from velab.errors import DataError

GEOMETRY_RTOL = 1e-6  # runs of one pipe: length, diameter, wall, alpha and density agree to this


@dataclass(frozen=True)
class CampaignRun:
    """One run of a campaign, as read from its file: what ``fit_record`` takes, plus its identity."""

    path: str
    time_s: np.ndarray
    head_m: np.ndarray
    trigger_time_s: float
    rig: Rig
    record_rate_hz: float
    position_pct: np.ndarray | None = None
    head_sha256: str = ""
    # the heads of the rig's other transducers by name (``rig.sections``; ``head_m`` is the valve's)
    section_heads: dict = field(default_factory=dict)

    @classmethod
    def from_run(cls, run) -> "CampaignRun":
        """From a velab.runfiles.Run (the reader's own checks of the window are the caller's), every head it
        holds for its rig's transducers (``run_heads``)."""
        valve = run.rig.head_section.name
        others = {k: v for k, v in run_heads(run).items() if k != valve}
        return cls(str(run.path), run.time_s, run.head_m, run.trigger_time_s, run.rig, run.sample_rate_hz,
                   run.channels.get("valve_position"), head_sha256(run.time_s, run.head_m), others)

    def heads(self) -> dict:
        """Each transducer's absolute head by name: the valve's (``head_m``) and the others'."""
        return {self.rig.head_section.name: self.head_m, **self.section_heads}


def run_heads(run) -> dict:
    """Each transducer's absolute head of a run read back from its file (velab.runfiles.reader.Run), by name:
    the channel ``rig.section_channel`` names (``head`` for the valve's, ``head_NAME`` for the others).
    DataError (one line, naming the file and the channel) for a transducer the file has no channel of."""
    rig = run.rig
    out = {}
    for sec in rig.sections:
        ch = rig.section_channel(sec)
        h = run.head_m if ch == "head" else run.channels.get(ch)
        if h is None:
            raise DataError(f"{run.path}: no channel {ch!r} for the transducer {sec.name!r} of its rig "
                            f"(channels: head, {', '.join(sorted(run.channels))})")
        out[sec.name] = h
    return out


def head_sha256(time_s, head_m) -> str:
    """The content hash naming a run in a joint fit: sha256 of its time axis and head (float64 bytes).
    Not of the file, which changes when a fit is saved into it."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(time_s, dtype="<f8").tobytes())
    h.update(np.ascontiguousarray(head_m, dtype="<f8").tobytes())
    return h.hexdigest()


def check_same_pipe(runs: list[CampaignRun]) -> None:
    """Runs of one pipe: the same geometry, constraint and fluid density (Q0, friction law, valve and
    manoeuvre may differ). Raises DataError naming the first run that differs."""
    ref = runs[0]

    def key(r: CampaignRun):
        p = r.rig.pipe
        return {"length_m": p.length_m, "inner_diameter_m": p.inner_diameter_m,
                "wall_thickness_m": p.wall_thickness_m, "constraint_alpha": p.constraint_alpha,
                "density_kg_m3": r.rig.fluid.density_kg_m3}

    k0 = key(ref)
    for r in runs[1:]:
        for name, v in key(r).items():
            if not math.isclose(v, k0[name], rel_tol=GEOMETRY_RTOL):
                raise DataError(f"{r.path}: another pipe than {ref.path} ({name} {v:g} against {k0[name]:g}); "
                                f"a joint fit needs runs of one pipe")
