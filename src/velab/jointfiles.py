"""A joint fit's runs on disk: read and checked before anything is fitted, the result saved into each.

One place for `velab fit --joint` and the operator window's "Fit together" (velab.gui.archive_io):
every run is read and its window checked first (a missing or damaged file, a window the run does not
hold, a run given twice, runs of different pipes: DataError naming the file, nothing written); the
joint fit is then saved atomically into every run (velab.runfiles.fits.save_fit, kind "joint"),
each copy naming the other runs by path and the sha256 of their record.
"""

from __future__ import annotations

from pathlib import Path

from velab.errors import DataError
from velab.fitting.campaignrun import CampaignRun, check_same_pipe
from velab.fitting.jointresult import JOINT_KIND
from velab.runfiles.fits import save_fit, validate_fit_name
from velab.runfiles.h5open import RunStillOpen
from velab.runfiles.reader import read_run


def read_sources(paths, window_s: float | None) -> list[CampaignRun]:
    """The runs of a joint fit, read and checked (module docstring)."""
    paths = [str(p) for p in paths]
    if len(paths) < 2:
        raise DataError("a joint fit needs two or more runs")
    sources, seen = [], {}
    for path in paths:
        run = read_run(path)
        run.fit_window(window_s)  # gaps, NaN, a window longer than the run: named with the file
        src = CampaignRun.from_run(run)
        key = Path(path).resolve()
        if key in seen or src.head_sha256 in seen.values():
            raise DataError(f"{path}: given twice (the same run, or the same record in another file)")
        seen[key] = src.head_sha256
        sources.append(src)
    check_same_pipe(sources)
    return sources


def default_name(window_s: float, reduced: bool = False) -> str:
    """A joint fit's fit group's name: the window, and "_reduced" with the reduced models (as a single fit's,
    velab.runfiles.fits.default_fit_name: a fit with them does not overwrite one without)."""
    return f"joint_w{window_s:g}s" + ("_reduced" if reduced else "")


def save_joint(result, sources: list[CampaignRun], name: str) -> list[str]:
    """Save the joint fit into every run (module docstring); returns the paths written. A run still
    open for writing is skipped with a note in the result; a write error is DataError naming the run
    (and the runs already written)."""
    name = validate_fit_name(name)
    saved = []
    for i, src in enumerate(sources):
        doc = result.to_dict() | {"run_index": i, "other_runs": [
            {"path": o.path, "resolved_path": str(Path(o.path).resolve()), "head_sha256": o.head_sha256}
            for j, o in enumerate(sources) if j != i]}
        try:
            save_fit(src.path, doc, name, kind=JOINT_KIND)
            saved.append(src.path)
        except RunStillOpen as exc:
            result.notes.append(f"not saved into {src.path}: {exc}")
        except OSError as exc:
            raise DataError(f"{src.path}: cannot write the joint fit into the run: {exc}"
                            + (f" (already saved into {', '.join(saved)})" if saved else "")) from None
    return saved
