"""The one call into the fitter for a :class:`~velab.fitservice.request.FitRequest`.

:func:`execute` is what every backend of the fit service runs (a thread of this process, the fit
process of velab.fit_worker, a Dask worker): the same function with the same request, so a fit
gives the same result bit for bit wherever it runs. It calls only the fitter's public entry points
(velab.fitting.entry.fit_record / fit_run, velab.fitting.joint.fit_joint) with the request's
FitOptions, and reads run files read-only: it never writes one (the caller saves).

A run file's request checks what ``velab fit`` checks before fitting: the bounded work of the window
(velab.bounds) and, when the caller will save the fit (``RunFile.will_save``), that the run can take
it (not open for writing, not damaged: :func:`save_refusal`). The fitter is imported when a fit
runs, not with this module (scipy; the recorder may never fit in its own process).
"""

from __future__ import annotations

from velab import bounds
from velab.errors import DataError, UnavailableError
from velab.fitservice.request import FitRequest, Record, RunFile, RunFiles


def save_refusal(run):
    """The error a fit that would be saved into ``run`` gets, or None: a run still open for writing (the
    recorder running, or killed: a storage matter, exit 5) or a damaged one (velab.runfiles.soundness, exit 2).
    The error's ``refusal`` is the batch's named reason (velab.batch.task.REFUSALS)."""
    if run.open_for_write:
        exc = UnavailableError(f"{run.path}: the run is still open for writing (being recorded, or its writer was "
                               f"killed): nothing fitted; --no-save fits it without saving, `velab recover "
                               f"{run.path}` writes a closed copy")
        exc.refusal = "run open"
        return exc
    if run.damage:
        exc = DataError(f"{run.path}: damaged run ({run.damage}): velab fit does not write into it; "
                        f"--no-save fits it without saving")
        exc.refusal = "damaged run"
        return exc
    return None


def save_note(run) -> str:
    """The note of a fit of a run that cannot take it, made without saving."""
    what = "open for writing" if run.open_for_write else f"damaged ({run.damage})"
    return f"the run is {what}: fitted with --no-save, nothing written into it"


def execute(request: FitRequest, progress=None, sources=None):
    """Run the fit ``request`` describes here; ``progress(done, total, name)`` after each model (it may
    raise to stop the fit). Returns the SweepResult (a RunFile or a Record: a sections result for a rig
    with several transducers) or the JointResult
    (RunFiles). Raises the fitter's DataError (one line) for bad data or choices.

    ``sources``: a RunFiles request's runs already read in this process (velab.jointfiles.read_sources of
    its paths and window: ``velab fit --joint`` reads them to check them before the fit, then saves and
    draws the fit with them), fitted as they are instead of read again; they must be the request's paths,
    in its order (else ValueError). A request sent to another process carries its paths only (it stays
    small and picklable), and the runs are read there."""
    src = request.source
    opts = request.choices
    if sources is not None and (not isinstance(src, RunFiles) or tuple(s.path for s in sources) != src.paths):
        raise ValueError("the runs given are not the request's: " + ", ".join(s.path for s in sources))
    if isinstance(src, Record):
        return _record(request, src, opts, progress)
    if isinstance(src, RunFile):
        return _run_file(request, src, opts, progress)
    if isinstance(src, RunFiles):
        return _joint(request, src, opts, progress, sources)
    raise DataError(f"nothing to fit: {type(src).__name__}")


def _record(request: FitRequest, src: Record, opts, progress):
    from velab.fitting import entry  # (looked up when called: the module's entry points as they are now)

    args = dict(t_s=src.t_s, head_m=src.head_m, trigger_time_s=src.trigger_time_s, rig=src.rig,
                window_s=request.window_s, record_rate_hz=src.record_rate_hz, position_pct=src.position_pct)
    return entry.fit_record(progress=progress, options=opts,
                            section_heads=dict(src.section_heads) or None, **args)


def _run_file(request: FitRequest, src: RunFile, opts, progress):
    from velab.fitting.entry import fit_run
    from velab.runfiles.reader import read_run

    run = read_run(src.path)
    window = request.window_s
    span = window if window is not None else run.duration_after_trigger_s
    work = bounds.work_problem(run.rig, span)  # bounded work (velab.bounds), before any fit
    if work:
        raise DataError(f"{src.path}: --window {span:g} s: {work}")
    refused = save_refusal(run)
    if refused is not None and src.will_save:
        raise refused  # said before the fit, not after it
    result = fit_run(run, window, opts, progress=progress)
    result.settings = result.settings.replace(window_s_requested=window)
    if refused is not None:
        result.notes.append(save_note(run))
    return result


def _joint(request: FitRequest, src: RunFiles, opts, progress, sources=None):
    from velab.fitting.joint import fit_joint
    from velab.jointfiles import read_sources

    if sources is None:
        sources = read_sources(src.paths, request.window_s)
    result = fit_joint(sources, request.window_s, opts, progress=progress)
    result.settings = result.settings.replace(window_s_requested=request.window_s)
    return result
