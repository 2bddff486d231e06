"""Run a batch's tasks on a Dask ``distributed`` cluster (``velab fit --scheduler ADDRESS``).

Dask and distributed are the optional extra ``velab[cluster]``: they are imported only here,
when a batch is sent to a scheduler, and their absence is a one-line error naming the extra.
Each worker reads its run from the shared storage (the path the client resolved, so every
machine must mount the archive at the same place) and returns the fit as plain data; the
client writes the fits (velab.batch.runner). A worker that dies mid-fit is replaced by the
scheduler, which runs the task again elsewhere; a task that kills workers again and again
(``KilledWorker``) becomes a ``worker lost`` failure, and a lost scheduler turns every fit
that had not come back into a ``scheduler lost`` failure. Nothing is written by a worker.
"""

from __future__ import annotations

import logging
import os
import uuid
from typing import Iterator

from velab.batch.task import failure, fit_one, worker_version
from velab.errors import UnavailableError, VelabError, one_line
from velab.version import __version__

EXTRA = "velab[cluster]"
CONNECT_TIMEOUT_S = 10.0
WORKERS_TIMEOUT_S = 30.0  # a scheduler with no worker yet: how long to wait for the first one


class MissingExtra(VelabError):
    """``--scheduler`` without dask/distributed installed."""


def import_distributed():
    """The ``distributed`` module, or a one-line error naming the extra that brings it."""
    try:
        import dask  # noqa: F401
        import distributed
    except ImportError as exc:
        raise MissingExtra(f"--scheduler needs dask and distributed, the optional extra {EXTRA}: "
                           f"pip install '{EXTRA}' ({exc})") from None
    return distributed


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


def outcomes(compute, paths: list[str], opts: dict, address: str) -> Iterator[dict]:
    """The outcome of every run of ``paths`` fitted on the cluster, in the order they complete."""
    distributed = import_distributed()
    _quiet_distributed_logs()
    client = connect(address)
    batch = uuid.uuid4().hex[:12]
    futures = {}
    try:
        for i, p in enumerate(paths):
            # the worker sees the archive at the same absolute path (shared storage)
            fut = client.submit(fit_one, compute, os.path.abspath(p), opts, key=f"velab-fit-{batch}-{i}",
                                pure=False, retries=0)
            futures[fut] = p
        for fut in distributed.as_completed(list(futures), loop=client.loop):
            yield _outcome(fut, futures[fut], distributed)
    finally:
        if futures:
            try:
                client.cancel(list(futures))
            except Exception:  # the scheduler is gone: nothing left to cancel
                pass
        client.close(timeout=CONNECT_TIMEOUT_S)


def _outcome(fut, path: str, distributed) -> dict:
    """The outcome of one finished, failed or cancelled task, with the user's own path."""
    try:
        if fut.status == "finished":
            o = fut.result()
            o["path"] = path
            if o.get("velab_version") != __version__:
                return failure(path, "version mismatch", f"fitted by velab {o.get('velab_version')} on "
                               f"{o.get('worker')}, this client runs {__version__}: not saved")
            return o
        if fut.status == "error":
            exc = fut.exception()
            if isinstance(exc, distributed.KilledWorker):
                return failure(path, "worker lost", f"the workers fitting this run died ({one_line(exc)})")
            return failure(path, "fit error", f"on a worker: {type(exc).__name__}: {exc}")
        return failure(path, "scheduler lost", f"the connection to the scheduler was lost before this run's "
                       f"fit came back (task {fut.status})")
    except Exception as exc:  # the result could not be fetched: the scheduler or the connection went
        return failure(path, "scheduler lost", f"the fit could not be fetched: {type(exc).__name__}: {exc}")


def _quiet_distributed_logs() -> None:
    """distributed logs connection trouble as multi-line tracebacks, from its own thread and until the
    process ends; velab reports it per run instead (``-vv`` keeps them)."""
    if logging.getLogger("velab").isEnabledFor(logging.DEBUG):
        return
    # dask's logging config gives some children their own level (distributed.client: warning)
    for name in ["distributed", *logging.root.manager.loggerDict]:
        if name == "distributed" or name.startswith("distributed."):
            logging.getLogger(name).setLevel(logging.CRITICAL)
