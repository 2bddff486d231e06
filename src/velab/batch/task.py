"""One run of a batch, fitted where the task runs (a local process or a Dask worker).

:func:`fit_one` reads the run (read-only), fits it with the single-run fit path it is given
(``velab.commands.fit.fit_file``, passed in so that the batch follows that path whatever it
becomes, and without an import cycle), and returns an *outcome*: plain data (dicts, lists,
numbers, strings) that pickles anywhere and that :func:`velab.runfiles.fits.save_fit` takes
as it is. It never writes the run: the batch's client does, one file at a time. It never
raises for a bad run either: the failure comes back as data with a named reason and the
exit code the single-run path would have given.

A run the fit could not be saved into (still open for writing, or damaged: velab.runfiles.soundness)
is *refused* before it is fitted, as ``velab fit RUN`` refuses it, unless the batch saves nothing
(``--no-save``): its outcome says ``refused`` with the named reason and the single-run exit code.
"""

from __future__ import annotations

import os
import socket
import time

from velab.errors import ExitCode, VelabError, one_line
from velab.version import __version__

# the named reasons of a failed run (docs/cluster.md); the exit code goes with the reason
REASONS = {
    "bad input": ExitCode.BAD_INPUT,           # the run file, or the fit settings on it (VelabError, code 2)
    "refused": ExitCode.REFUSED,
    "storage failure": ExitCode.FAILURE,       # a VelabError with code 5, an OSError
    "fit error": ExitCode.FAILURE,             # an unexpected exception inside the fit (a bug, or a damaged file)
    "not saved": ExitCode.FAILURE,             # fitted, but the client could not write the fit into the run
    "worker lost": ExitCode.FAILURE,           # the process fitting the run died (crash, OOM kill, a lost machine)
    "scheduler lost": ExitCode.FAILURE,        # the connection to the Dask scheduler went before the fit came back
    "version mismatch": ExitCode.FAILURE,      # a worker runs another velab than the client
    "interrupted": ExitCode.INTERRUPTED,
    # refused before fitting, as `velab fit RUN` refuses them (velab.commands.fit._refused_save)
    "run open": ExitCode.FAILURE,              # still open for writing: being recorded, or its writer killed
    "damaged run": ExitCode.BAD_INPUT,         # its structure is not a run's (velab.runfiles.soundness)
}
# the reasons of a run refused (not fitted, nothing written) rather than failed
REFUSALS = ("run open", "damaged run")


def reason_of(exc: BaseException) -> str:
    """The named reason of an exception raised by the fit of one run."""
    refusal = getattr(exc, "refusal", None)  # set by the single-run path on a run it will not fit
    if refusal in REFUSALS:
        return refusal
    if isinstance(exc, VelabError):
        code = ExitCode(exc.exit_code)
        return {ExitCode.BAD_INPUT: "bad input", ExitCode.REFUSED: "refused"}.get(code, "storage failure")
    if isinstance(exc, OSError):
        return "storage failure"
    return "fit error"


def failure(path: str, reason: str, message: str, **extra) -> dict:
    """The outcome of a run that gave no fit: ``reason`` is one of :data:`REASONS`; ``status`` is
    ``refused`` for one of :data:`REFUSALS`, else ``failed``."""
    message = one_line(message)
    prefix = f"{path}: "
    if message.startswith(prefix):  # the path is the outcome's; keep the message to what went wrong
        message = message[len(prefix):]
    status = "refused" if reason in REFUSALS else "failed"
    return {"path": path, "ok": False, "status": status, "reason": reason, "error": message,
            "exit_code": int(REASONS[reason]), **extra}


def where() -> str:
    """This process, for the summary: ``host:pid``."""
    return f"{socket.gethostname()}:{os.getpid()}"


def fit_one(compute, path: str, opts: dict) -> dict:
    """Fit the run at ``path`` with ``compute(path, opts, many=True) -> (SweepResult, name)``.

    ``opts`` are ``velab fit``'s options; the fit is made with saving off (the client saves), but
    ``client_saves`` tells the fit path that it will be saved, so a run that cannot be saved into is
    refused before its fit (not fitted, then refused at the save). Returns ``{path, ok: True,
    fit: result.to_dict(), seconds, velab_version, worker}`` or a :func:`failure`.
    """
    t0 = time.perf_counter()
    info = {"velab_version": __version__, "worker": where()}
    try:
        saves = bool(opts.get("save", True))
        result, _ = compute(path, {**opts, "save": False, "client_saves": saves}, many=True)
        fit = result.to_dict()
    except Exception as exc:  # one bad run must not stop the batch: the failure travels as data
        message = str(exc) if isinstance(exc, (VelabError, OSError)) else f"{type(exc).__name__}: {exc}"
        return failure(path, reason_of(exc), message, seconds=time.perf_counter() - t0, **info)
    return {"path": path, "ok": True, "fit": fit, "seconds": time.perf_counter() - t0, **info}


def worker_version() -> str:
    """The velab version of the process that runs this (asked of every Dask worker before a batch)."""
    return __version__
