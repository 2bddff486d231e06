"""The outcome of one run of a batch, as plain data, from its fit's Future (velab.fitservice).

:func:`outcome_of` turns the finished fit of a run into an *outcome*: plain data (dicts, lists,
numbers, strings) that :func:`velab.runfiles.fits.save_fit` takes as it is; a failure comes back as
data with a named reason and the exit code the single-run path would have given.

A run the fit could not be saved into (still open for writing, or damaged: velab.runfiles.soundness)
is *refused* before it is fitted, as ``velab fit RUN`` refuses it, unless the batch saves nothing
(``--no-save``): its outcome says ``refused`` with the named reason and the single-run exit code.
"""

from __future__ import annotations

from velab.errors import ExitCode, VelabError, one_line
from velab.fitservice.errors import FitWorkerDied, WorkerMismatch
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


def outcome_of(path: str, fut, twice: bool = False) -> dict:
    """The outcome of the finished fit ``fut`` (a velab.fitservice FitFuture) of the run at ``path``:
    ``{path, ok: True, fit: result.to_dict(), notes, seconds, velab_version, worker}`` or a :func:`failure`
    (``twice``: the run had been tried again after its process died)."""
    info = {"seconds": fut.seconds, "velab_version": __version__, "worker": fut.where}
    exc = fut.exception()
    if exc is None:
        result = fut.result()
        notes = [n for n in result.notes if n.endswith("nothing written into it")]  # (execute.save_note)
        return {"path": path, "ok": True, "fit": result.to_dict(), "notes": notes, **info}
    if isinstance(exc, WorkerMismatch):
        return failure(path, "version mismatch", str(exc))
    if isinstance(exc, FitWorkerDied):
        if exc.reason == "scheduler lost":
            return failure(path, "scheduler lost", str(exc))
        if twice:
            return failure(path, "worker lost", "the process fitting this run died (twice: a crash in a library "
                           "or an out-of-memory kill while reading or fitting it)", **info)
        return failure(path, "worker lost", str(exc), **info)
    message = str(exc) if isinstance(exc, (VelabError, OSError)) else f"{type(exc).__name__}: {exc}"
    return failure(path, reason_of(exc), message, **info)
