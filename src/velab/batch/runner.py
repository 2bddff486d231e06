"""Drive a batch: tasks run locally or on a cluster; the fits are written here, one file at a time.

Only this process (the client) writes run files, and only through the atomic
:func:`velab.runfiles.fits.save_fit`: a run on shared storage is never written by two
processes, and a run whose fit failed, or never came back, or that was refused (open for
writing, damaged: velab.batch.task), is left exactly as it was.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

from velab.batch import local
from velab.batch.task import failure
from velab.errors import VelabError
from velab.runfiles.fits import save_fit
from velab.runfiles.h5open import RunStillOpen

BAR_WIDTH = 20


@dataclass
class Batch:
    """What a batch did: one outcome per run, in the order the runs were given."""

    outcomes: list[dict]
    seconds: float
    where: str  # "local, 2 processes" | "dask tcp://host:8786"
    scheduler: str | None = None
    jobs: int | None = 1  # None on a cluster
    extra: dict = field(default_factory=dict)


def run_batch(compute, paths: list[str], opts: dict, *, jobs: int = 1, scheduler: str | None = None,
              progress=None) -> Batch:
    """Fit every run of ``paths`` with ``compute`` (velab.commands.fit.fit_file) and save the fits.

    ``opts`` are ``velab fit``'s options (``save``: write the fits; ``name``: the fit group).
    ``scheduler``: a checked Dask scheduler address (velab.batch.address), else local processes.
    """
    t0 = time.perf_counter()
    if scheduler:
        from velab.batch import cluster  # distributed is imported there, only for a cluster batch

        stream = cluster.outcomes(compute, paths, opts, scheduler)
        where = f"dask {scheduler}"
    else:
        stream = local.outcomes(compute, paths, opts, jobs)
        n = local.processes_for(jobs, len(paths))
        where = f"local, {n} process{'es' if n > 1 else ''}" if n > 1 else "local, this process"
    done: dict[int, dict] = {}
    pending = {}  # path -> indices still waiting for their outcome (a path may be given twice)
    for i, p in enumerate(paths):
        pending.setdefault(p, []).append(i)
    failed = refused = 0
    for o in stream:
        if o["ok"]:
            o = _save(o, opts)
        refused += o.get("status") == "refused"
        failed += not o["ok"] and o.get("status") != "refused"
        done[pending[o["path"]].pop(0)] = o
        if progress is not None:
            progress.update(_bar(len(done), len(paths), failed, o["path"], refused), force=True)
    outcomes = [done.get(i) or failure(p, "scheduler lost", "no outcome came back for this run")
                for i, p in enumerate(paths)]
    return Batch(outcomes, time.perf_counter() - t0, where, scheduler, None if scheduler else jobs)


def _save(o: dict, opts: dict) -> dict:
    """Write the fit of a successful outcome into its run (client side, atomic); the outcome's status."""
    if not opts.get("save", True):
        return {**o, "status": "fitted", "fit_name": None}
    try:
        name = save_fit(o["path"], o["fit"], opts.get("name"))
    except RunStillOpen as exc:
        # opened for writing after its fit was made (a recorder started on it meanwhile): refused as a run
        # found open before its fit is (velab.batch.task), the fit not written
        return failure(o["path"], "run open", f"{exc}: the fit made is not written", seconds=o["seconds"],
                       worker=o.get("worker"))
    except (VelabError, OSError) as exc:
        code = {"exit_code": int(exc.exit_code)} if isinstance(exc, VelabError) else {}
        msg = str(exc) if isinstance(exc, VelabError) else f"cannot write the fit into the run: {exc.strerror or exc}"
        return failure(o["path"], "not saved", msg, seconds=o["seconds"], worker=o.get("worker"), **code)
    return {**o, "status": "saved", "fit_name": name}


def _bar(done: int, total: int, failed: int, last: str, refused: int = 0) -> str:
    full = BAR_WIDTH * done // max(total, 1)
    text = f"velab fit [{'#' * full}{'.' * (BAR_WIDTH - full)}] {done}/{total} runs"
    if failed:
        text += f", {failed} failed"
    if refused:
        text += f", {refused} refused"
    return f"{text}, last {Path(last).name}"
