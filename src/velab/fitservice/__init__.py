"""One way to run a fit: ``FitService.submit(FitRequest) -> Future`` (docs/fit-service.md).

A :class:`FitRequest` (velab.fitservice.request) says what to fit -- a run file, several run files
fitted jointly, or a record in memory as the recorder holds it -- over which window, with which
choices (velab.fitting.options.FitOptions). A :class:`FitService` runs it on one backend:

* ``FitService.in_thread()`` -- a thread of this process (velab.fitservice.thread);
* ``FitService.processes(n)`` -- velab's fit processes, pre-started at a lower priority
  (velab.fit_worker; velab.fitservice.process);
* ``FitService.dask(address)`` -- a Dask cluster (the optional extra ``velab[cluster]``;
  velab.fitservice.cluster).

Every backend runs the same :func:`velab.fitservice.execute.execute`, so a result does not depend on
where it was computed. The Future ends with the fit's result, the fit's own user error (VelabError,
one line) or a named exception (velab.fitservice.errors: FitCancelled, FitWorkerDied, FitFailed);
progress comes as FitProgress messages.

The names below are imported on first use (PEP 562): ``velab.fitservice.errors`` and ``.request`` load
neither the fitter nor the process machinery.
"""

from __future__ import annotations

from velab.lazy import lazy_exports

_EXPORTS = {
    "FitService": "service",
    "FitRequest": "request", "RunFile": "request", "RunFiles": "request",
    "Record": "request", "FitProgress": "request",
    "FitFuture": "future",
    "FitCancelled": "errors", "FitWorkerDied": "errors", "FitFailed": "errors", "WorkerMismatch": "errors",
}  # (not ``execute``: a name the same as its module's is the module once that is imported; import it from there)
__all__ = list(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, globals(), _EXPORTS)
