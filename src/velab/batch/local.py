"""Run a batch's tasks on this machine: in this process (``--jobs 1``) or in a process pool.

:func:`outcomes` yields one outcome (velab.batch.task) per run as each completes. A worker
process that dies (a crash in a library, an out-of-memory kill) breaks the whole pool, so the
runs it took down with it are tried again one at a time, each in a pool of its own: the run
that kills its process again is reported as ``worker lost`` and the others get their fits.
"""

from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from typing import Iterator

from velab.batch.task import failure, fit_one


def processes_for(jobs: int, runs: int) -> int:
    """Processes used for ``--jobs`` over ``runs`` runs: never more than the runs or the cores."""
    return max(1, min(jobs, runs, os.cpu_count() or 1))


def outcomes(compute, paths: list[str], opts: dict, jobs: int) -> Iterator[dict]:
    """The outcome of every run of ``paths``, in the order they complete."""
    if processes_for(jobs, len(paths)) == 1:
        for p in paths:
            yield fit_one(compute, p, opts)
        return
    broken: list[str] = []
    yield from _pool(compute, paths, opts, processes_for(jobs, len(paths)), broken)
    for p in broken:  # isolate the run that killed its worker: one pool per run
        lost: list[str] = []
        yield from _pool(compute, [p], opts, 1, lost)
        for q in lost:
            yield failure(q, "worker lost", "the process fitting this run died (twice: a crash in a library "
                          "or an out-of-memory kill while reading or fitting it)")


def _pool(compute, paths: list[str], opts: dict, workers: int, broken: list[str]) -> Iterator[dict]:
    ex = ProcessPoolExecutor(max_workers=workers)
    futures = {ex.submit(fit_one, compute, p, opts): p for p in paths}
    try:
        for fut in as_completed(futures):
            try:
                yield fut.result()
            except BrokenProcessPool:
                broken.append(futures[fut])
    finally:
        # normal end, or the consumer stopped (Ctrl-C): nothing new starts; running fits end
        ex.shutdown(wait=True, cancel_futures=True)
