"""``FitService.submit(FitRequest) -> FitFuture``: the one way velab runs a fit (docs/fit-service.md).

The service validates nothing the request has not (a FitRequest is checked when it is made) and
adds nothing to the fit: it hands the request to its backend and returns the backend's Future.
Progress: ``submit(request, progress=sink)`` calls ``sink(FitProgress)`` after each model, from the
backend's thread (a GUI or a recorder posts it to its own thread). Thread-safe.
"""

from __future__ import annotations

from velab.fitservice.future import FitFuture
from velab.fitservice.request import FitRequest


class FitService:
    """Runs fit requests on one backend: ``in_thread()``, ``processes(n)`` or ``dask(address)``."""

    def __init__(self, backend):
        self.backend = backend

    @classmethod
    def in_thread(cls) -> "FitService":
        """Each fit on a thread of this process."""
        from velab.fitservice.thread import ThreadBackend

        return cls(ThreadBackend())

    @classmethod
    def processes(cls, n: int = 1, *, replace_dead: bool = True, start: bool = False) -> "FitService":
        """Fits in ``n`` fit processes (velab.fit_worker); ``start``: start them now (OSError if one
        cannot be started); ``replace_dead``: a process that died is replaced for the next fits."""
        from velab.fitservice.process import ProcessBackend

        backend = ProcessBackend(n, replace_dead=replace_dead)
        if start:
            backend.start()
        return cls(backend)

    @classmethod
    def dask(cls, address: str) -> "FitService":
        """Fits on the Dask cluster of the scheduler at ``address`` (connects now: UnavailableError, or
        MissingExtra without the velab[cluster] extra)."""
        from velab.fitservice.cluster import DaskBackend

        return cls(DaskBackend(address))

    @property
    def name(self) -> str:
        return self.backend.name

    @property
    def alive(self) -> bool:
        """The backend can take fits (its process is running, its scheduler connected)."""
        return self.backend.alive

    def submit(self, request: FitRequest, progress=None) -> FitFuture:
        """Run ``request``; its Future (velab.fitservice.future.FitFuture)."""
        if not isinstance(request, FitRequest):
            raise TypeError(f"FitService.submit takes a FitRequest, not {type(request).__name__}")
        return self.backend.submit(request, progress)

    def close(self) -> None:
        """No more fits; a process backend gives its processes back (busy ones are ended)."""
        self.backend.close()

    def __enter__(self) -> "FitService":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
