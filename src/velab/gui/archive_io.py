"""File work of the archive browser, run on worker threads (no Qt here).

Reading a run (also one still being written: SWMR), reading its stored fits, the fit service's
requests of a re-fit and of a joint fit and saving their results, exporting a CSV and the report figure.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from velab.runfiles.summary import describe
from velab.errors import DataError


@dataclass
class LoadedRun:
    run: object  # velab.runfiles.Run
    summary: str
    fits: dict = field(default_factory=dict)  # fit group name -> SweepResult
    fit_errors: dict = field(default_factory=dict)


def load_run(path) -> LoadedRun:
    from velab.runfiles.fits import read_fit_group
    from velab.runfiles import open_run_file, read_run

    run = read_run(path)
    try:
        summary = describe(run)
    except Exception as exc:  # describe() also opens the file for the fits; a live file may race
        summary = f"{run.path}\n  (summary unavailable: {exc})"
    fits, errors = {}, {}
    try:
        with open_run_file(path) as fh:
            group = fh["entry"].get("fits")
            if group is not None:
                for name, g in group.items():
                    if isinstance(g, h5py.Group):
                        try:
                            fits[name] = read_fit_group(g)
                        except Exception as exc:
                            errors[name] = str(exc)
    except (OSError, KeyError) as exc:
        errors["(file)"] = str(exc)
    return LoadedRun(run, summary, fits, errors)


@dataclass
class RefitOptions:
    models: str = "0-6"
    window_s: float | None = 20.0
    method: str = "auto"
    reduced: bool = False
    starts: int | None = None
    polish: bool = True
    save: bool = True
    name: str | None = None


@dataclass
class RefitOutcome:
    result: object  # SweepResult
    t: np.ndarray
    h: np.ndarray
    rig: object
    saved_as: str | None
    note: str = ""


def refit_request(path, opts: RefitOptions):
    """The fit service's request for a re-fit of the run at ``path`` (velab.fitservice; the run is saved into
    afterwards, unless it is still being written: :func:`store_refit`). DataError for bad options."""
    from velab.fitservice.request import FitRequest, RunFile

    return FitRequest(RunFile(str(path)), opts.window_s, _choices(opts), label=f"refit-{Path(path).name}")


def _choices(opts: RefitOptions):
    """The fit's options from the Re-fit settings (a re-fit's and a joint fit's: every search option is both's)."""
    from velab.fitting.options import FitOptions

    return FitOptions(models=opts.models, method=opts.method, reduced=opts.reduced, starts=opts.starts,
                      polish=opts.polish)


def joint_request(paths, opts: RefitOptions):
    """The fit service's request for the joint fit of the runs (``velab fit --joint`` with the Re-fit settings'
    models, window and search: the method, the reduced models, the starts, the polish). DataError for bad
    options."""
    from velab.fitservice.request import FitRequest, RunFiles

    return FitRequest(RunFiles(tuple(str(p) for p in paths)), opts.window_s, _choices(opts), label="joint")


def store_refit(path, result, opts: RefitOptions) -> RefitOutcome:
    """After a re-fit of the run at ``path``: its window for the fit panel, and the fit saved into the run
    (unless ``opts.save`` is off or the run is still being written: then a note says why)."""
    from velab.runfiles import read_run
    from velab.runfiles.fits import save_fit

    run = read_run(path)
    t, h = run.fit_window(opts.window_s)
    saved, note = None, ""
    if opts.save:
        if run.incomplete:
            note = "not saved: the run is still being written (or its writer never closed it)"
        else:
            try:
                saved = save_fit(path, result, opts.name)
            except (OSError, DataError) as exc:  # e.g. flagged open for write: velab recover first
                note = f"not saved: {exc}"
    return RefitOutcome(result, t, h, run.rig, saved, note)


def store_joint(paths, result, opts: RefitOptions) -> str | None:
    """After a joint fit: saved into every run (velab.jointfiles), the fit group's name; None when not saved."""
    from velab.jointfiles import default_name, read_sources, save_joint

    if not opts.save:
        return None
    name = opts.name or default_name(opts.window_s, opts.reduced)
    save_joint(result, read_sources(paths, opts.window_s), name)
    return name


def export_csv(run, path) -> Path:
    """Write the run's samples (time from the trigger, head, head perturbation, other channels) as CSV."""
    path = Path(path)
    cols = {"time_s": run.time_s, "head_m": run.head_m, "head_perturbation_m": run.head_perturbation()}
    for name, values in run.channels.items():
        if np.shape(values) == np.shape(run.time_s):
            unit = run.channel_units.get(name, "")
            cols[f"{name}_{unit}".rstrip("_").replace("/", "per").replace("%", "pct").replace(" ", "")] = values
    names = list(cols)
    data = np.column_stack([np.asarray(cols[k], dtype=float) for k in names])
    with open(path, "w", newline="") as fh:
        fh.write(f"# velab run {run.path.name}: {run.title}\n")
        fh.write(f"# status {run.status}; start {run.start_time}; rig {run.rig.name}; "
                 f"{run.sample_rate_hz:g} Hz; steady head {run.steady_head_m:.4f} m; time from the trigger\n")
        w = csv.writer(fh)
        w.writerow(names)
        fmt = ["%.6f"] + ["%.6g"] * (len(names) - 1)
        np.savetxt(fh, data, delimiter=",", fmt=fmt)
    return path


def export_report_figure(path_run, result, path) -> Path:
    """The 2 x 2 report figure (velab.fitting.plots) of ``result`` on the run at ``path_run``."""
    from velab.fitting.plots import report_figure
    from velab.runfiles import read_run

    path = Path(path)
    if path.suffix.lower() not in (".png", ".pdf", ".svg"):
        raise DataError(f"{path}: use a .png, .pdf or .svg file name")
    run = read_run(path_run)
    window = result.window_s if result.window_s and math.isfinite(result.window_s) else None
    window = min(window, run.duration_after_trigger_s) if window else None
    t, h = run.fit_window(window)
    report_figure(t, h, run.rig, result, path, run=run)
    return path


def fit_window_of(path, window_s):
    """(t, h, rig) of a run's calibration window (time from the measured trigger, head perturbation)."""
    from velab.runfiles import read_run

    run = read_run(path)
    window = min(window_s, run.duration_after_trigger_s) if window_s else None
    t, h = run.fit_window(window)
    return t, h, run.rig


def list_runs(folder) -> list[Path]:
    folder = Path(folder)
    if not folder.is_dir():
        return []
    files = [p for p in folder.iterdir() if p.suffix.lower() in (".h5", ".hdf5", ".nxs") and p.is_file()]
    return sorted(files, key=lambda p: p.stat().st_mtime, reverse=True)


# ------------------------------------------------------------------ the run catalogue (velab.catalogue)


def index_folder(folder, on_rows, stop=None, progress=None):
    """The catalogue of ``folder`` on a worker thread: what the index holds at once, then what changed.

    ``on_rows(rows, replace)`` is called with the index's rows (``replace`` True: the first
    paint, from the index alone), then with each batch of rows read from new or changed files.
    Returns the up-to-date Listing. Run files are only read (in worker processes).
    """
    from velab.catalogue.index import Catalogue

    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(f"{folder}: no such folder")
    with Catalogue(roots=[folder]) as cat:
        on_rows(cat.cached([folder]).rows, True)
        # fresh worker processes (fork=False): a fork of the threaded GUI could inherit a lock (h5py's)
        # that another worker thread holds
        listing = cat.update([folder], stop=stop, fork=False, on_rows=lambda rows: on_rows(rows, False),
                             progress=(lambda d, t: progress(d, t, "indexing")) if progress else None)
    return listing


def export_rows(rows, path) -> Path:
    """The catalogue rows as CSV (every column, as ``velab runs --csv``)."""
    from velab.catalogue.query import to_csv

    path = Path(path)
    path.write_text(to_csv(list(rows)))
    return path
