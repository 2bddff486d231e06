"""Drive a batch through the fit service: the runs fitted here, in fit processes or on a Dask cluster;
the fits written here, one file at a time.

Each run is one :class:`velab.fitservice.FitRequest` (its file, the window, ``velab fit``'s choices);
``--jobs 1`` fits in this process (the service's in-process backend), ``--jobs N`` in N fit processes
(velab.fit_worker, at a lower priority), ``--scheduler ADDRESS`` on the Dask cluster. Each outcome is
plain data (velab.batch.task). A fit process that dies fails only the run it was fitting; that run is
tried once more in a fresh process, and the run that kills its process again is ``worker lost``.

Only this process (the client) writes run files, and only through the atomic
:func:`velab.runfiles.fits.save_fit`: a run on shared storage is never written by two
processes, and a run whose fit failed, or never came back, or that was refused (open for
writing, damaged: velab.fitservice.execute.save_refusal), is left exactly as it was.
"""

from __future__ import annotations

import sys
import time
from concurrent.futures import FIRST_COMPLETED, wait
from dataclasses import dataclass, field
from pathlib import Path

from velab.batch import local
from velab.batch.task import failure, outcome_of
from velab.errors import VelabError
from velab.fitservice.errors import FitWorkerDied
from velab.fitservice.service import FitService
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


def service_for(paths: list[str], jobs: int = 1, scheduler: str | None = None) -> tuple[FitService, str]:
    """The fit service a batch runs on, and where that is (the table's and the JSON's ``where``)."""
    if scheduler:
        return FitService.dask(scheduler), f"dask {scheduler}"
    n = local.processes_for(jobs, len(paths))
    if n == 1:
        return FitService.in_thread(), "local, this process"
    return FitService.processes(n), f"local, {n} processes"


def run_batch(request_of, paths: list[str], opts: dict, *, jobs: int = 1, scheduler: str | None = None,
              progress=None, service: FitService | None = None, plot=None) -> Batch:
    """Fit every run of ``paths`` and save the fits. ``request_of(path, opts)`` is the FitRequest of one run
    (velab.commands.fit.fit_request: passed in, so that the batch makes the single-run path's request
    whatever it becomes); ``opts`` are ``velab fit``'s options (``save``: write the fits; ``name``: the fit
    group). ``scheduler``: a checked Dask scheduler address (velab.batch.address), else ``jobs`` local
    processes; ``service``: a FitService to use instead (closed at the end). ``plot(path, result)`` writes
    a run's figure once its fit is saved."""
    t0 = time.perf_counter()
    where = "given service"
    if service is None:
        service, where = service_for(paths, jobs, scheduler)
    try:
        outcomes = _outcomes(service, paths, opts, request_of, progress, plot)
    finally:
        service.close()
    return Batch(outcomes, time.perf_counter() - t0, where, scheduler, None if scheduler else jobs)


def _outcomes(service, paths, opts, request_of, progress, plot) -> list[dict]:
    # this process fits one run at a time; fit processes and a cluster queue them all (and keep their own pace)
    limit = 1 if service.name == "thread" else len(paths)
    waiting = list(enumerate(paths))[::-1]
    futures: dict = {}
    pending: set = set()

    def send() -> None:
        while waiting and len(pending) < limit:
            i, p = waiting.pop()
            fut = service.submit(request_of(p, opts))
            futures[fut] = i
            pending.add(fut)

    send()
    retried: set[int] = set()
    done: dict[int, dict] = {}
    failed = refused = 0
    while pending:
        ready, _ = wait(pending, return_when=FIRST_COMPLETED)
        pending -= ready
        for fut in ready:
            i, path = futures[fut], paths[futures[fut]]
            exc = fut.exception()
            if isinstance(exc, FitWorkerDied) and exc.reason == "worker lost" and service.name == "process" \
                    and i not in retried:
                retried.add(i)  # the process died with this run: once more, in a fresh process
                again = service.submit(request_of(path, opts))
                futures[again] = i
                pending.add(again)
                continue
            o = outcome_of(path, fut, twice=i in retried)
            if o["ok"]:
                for note in o.pop("notes", ()):
                    print(f"velab: {path}: {note}", file=sys.stderr)
                o = _save(o, opts)
                if plot is not None and o["ok"]:
                    plot(path, fut.result())
            refused += o.get("status") == "refused"
            failed += not o["ok"] and o.get("status") != "refused"
            done[i] = o
            if progress is not None:
                progress.update(_bar(len(done), len(paths), failed, path, refused), force=True)
        send()
    return [done.get(i) or failure(p, "scheduler lost", "no outcome came back for this run")
            for i, p in enumerate(paths)]


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
