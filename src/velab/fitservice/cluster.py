"""The Dask backend: fits on a ``distributed`` cluster (``velab fit --scheduler ADDRESS``).

Dask and distributed are the optional extra ``velab[cluster]``: imported when a DaskBackend is made,
their absence a one-line error naming the extra (:class:`MissingExtra`). Each worker runs
:func:`run_on_worker` -- the same :func:`velab.fitservice.execute.execute` -- on the request, reading
run files from the shared storage at the path the client gives (every machine mounts the archive at
the same place), and returns the result with the worker's velab version and name; nothing is
written by a worker. Outcomes: a result from a worker running another velab is WorkerMismatch; a
task that killed its workers (``KilledWorker``) is FitWorkerDied("worker lost"); a lost scheduler
fails every fit not yet back with FitWorkerDied("scheduler lost"); the fit's own errors come back as
themselves. Dask reports no progress per model.
"""

from __future__ import annotations

import itertools
import logging
import os
import time
import uuid

from velab.errors import UnavailableError, VelabError, one_line
from velab.fitservice.errors import FitWorkerDied, WorkerMismatch
from velab.fitservice.execute import execute
from velab.fitservice.future import FitFuture, settle, this_process
from velab.fitservice.request import FitRequest, RunFile, RunFiles
from velab.version import __version__

EXTRA = "velab[cluster]"
CONNECT_TIMEOUT_S = 10.0
WORKERS_TIMEOUT_S = 30.0  # a scheduler with no worker yet: how long to wait for the first one


class MissingExtra(VelabError):
    """A Dask backend without dask/distributed installed."""


def import_distributed():
    """The ``distributed`` module, or a one-line error naming the extra that brings it."""
    try:
        import dask  # noqa: F401
        import distributed
    except ImportError as exc:
        raise MissingExtra(f"--scheduler needs dask and distributed, the optional extra {EXTRA}: "
                           f"pip install '{EXTRA}' ({exc})") from None
    return distributed


def worker_version() -> str:
    """The velab version of the process that runs this (asked of every Dask worker first)."""
    return __version__


def run_on_worker(request: FitRequest) -> dict:
    """The Dask task: the fit, and who made it (velab version, ``host:pid``, seconds)."""
    t0 = time.perf_counter()
    result = execute(request)
    return {"result": result, "velab_version": __version__, "worker": this_process(),
            "seconds": time.perf_counter() - t0}


def connect(address: str):
    """A Client of the scheduler at ``address`` with at least one worker running this velab."""
    distributed = import_distributed()
    try:
        client = distributed.Client(address, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        why = "" if "timed out" in str(exc).lower() else f": {one_line(exc)}"
        raise UnavailableError(f"--scheduler {address}: cannot connect within {CONNECT_TIMEOUT_S:g} s "
                               f"(is `dask scheduler` running there?){why}") from None
    try:
        try:
            client.wait_for_workers(1, timeout=WORKERS_TIMEOUT_S)
        except (TimeoutError, OSError):
            raise UnavailableError(f"--scheduler {address}: no worker joined within {WORKERS_TIMEOUT_S:g} s "
                                   "(start them with `dask worker ADDRESS`)") from None
        try:
            versions = client.run(worker_version)
        except Exception as exc:  # velab missing on a worker: unpickling the call fails there
            raise UnavailableError(f"--scheduler {address}: a worker cannot run velab "
                                   f"({type(exc).__name__}: {one_line(exc)}); install velab {__version__} "
                                   "on every worker") from None
        other = {w: v for w, v in versions.items() if v != __version__}
        if other:
            w, v = next(iter(other.items()))
            raise UnavailableError(f"--scheduler {address}: worker {w} runs velab {v}, this client {__version__} "
                                   f"({len(other)} of {len(versions)} workers differ); install the same velab "
                                   "on every worker")
    except BaseException:
        client.close()
        raise
    return client


def quiet_distributed_logs() -> None:
    """distributed logs connection trouble as multi-line tracebacks, from its own thread and until the
    process ends; velab reports it per fit instead (``-vv`` keeps them)."""
    if logging.getLogger("velab").isEnabledFor(logging.DEBUG):
        return
    for name in ["distributed", *logging.root.manager.loggerDict]:
        if name == "distributed" or name.startswith("distributed."):
            logging.getLogger(name).setLevel(logging.CRITICAL)


def _absolute(request: FitRequest) -> FitRequest:
    """The request with its run files' absolute paths (the worker sees the archive at the same place)."""
    from dataclasses import replace

    src = request.source
    if isinstance(src, RunFile):
        return replace(request, source=replace(src, path=os.path.abspath(src.path)))
    if isinstance(src, RunFiles):
        return replace(request, source=RunFiles(tuple(os.path.abspath(p) for p in src.paths)))
    return request


class DaskBackend:
    """Fits on the cluster of the scheduler at ``address`` (module docstring). Thread-safe."""

    name = "dask"

    def __init__(self, address: str):
        self._distributed = import_distributed()
        quiet_distributed_logs()
        self.address = address
        self.client = connect(address)
        self._batch = uuid.uuid4().hex[:12]
        self._n = itertools.count(1)  # (thread-safe: the keys of this client's tasks)

    @property
    def alive(self) -> bool:
        return self.client.status == "running"

    def submit(self, request: FitRequest, progress=None) -> FitFuture:
        fut = FitFuture(request)
        try:
            key = f"velab-fit-{self._batch}-{next(self._n)}"
            task = self.client.submit(run_on_worker, _absolute(request), key=key, pure=False, retries=0)
        except Exception as exc:  # noqa: BLE001 - the scheduler is gone
            settle(fut, exc=FitWorkerDied(f"the fit could not be sent to the scheduler: {one_line(exc)}",
                                          "scheduler lost"))
            return fut
        fut.bind(lambda kill: self._cancel(task))
        task.add_done_callback(lambda t: self._finished(fut, t))
        return fut

    def _cancel(self, task) -> None:
        try:
            self.client.cancel([task])
        except Exception:  # noqa: BLE001 - the scheduler is gone: nothing left to cancel
            pass

    def _finished(self, fut: FitFuture, task) -> None:
        try:
            if task.status == "finished":
                out = task.result()
                fut.where, fut.seconds = out["worker"], out["seconds"]
                if out.get("velab_version") != __version__:
                    settle(fut, exc=WorkerMismatch(f"fitted by velab {out.get('velab_version')} on {out['worker']}, "
                                                   f"this client runs {__version__}: not taken"))
                else:
                    settle(fut, out["result"])
            elif task.status == "error":
                exc = task.exception()
                if isinstance(exc, self._distributed.KilledWorker):
                    settle(fut, exc=FitWorkerDied(f"the workers fitting it died ({one_line(exc)})", "worker lost"))
                else:
                    settle(fut, exc=exc)
            else:
                settle(fut, exc=FitWorkerDied(f"the connection to the scheduler was lost before the fit came back "
                                              f"(task {task.status})", "scheduler lost"))
        except Exception as exc:  # noqa: BLE001 - the result could not be fetched: the scheduler went
            settle(fut, exc=FitWorkerDied(f"the fit could not be fetched: {type(exc).__name__}: {exc}",
                                          "scheduler lost"))

    def close(self) -> None:
        try:
            self.client.close(timeout=CONNECT_TIMEOUT_S)
        except Exception:  # noqa: BLE001 - closing a client of a lost scheduler
            pass
