"""``velab fit``: calibrate EL/Sm models on run files and rank them by AIC."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from velab.batch.address import scheduler_address
from velab.commands.common import ProgressLine, add_json_option, check_output_path, float_range, int_range, write_json
from velab.errors import DataError, ExitCode

# velab.fitting.sweep.METHODS, named here so that building the parser does not import the
# fitter (scipy); run() checks the option against the fitter's own list.
METHOD_NAMES = "auto, least-squares, nelder-mead, evolution"
PLOT_SUFFIXES = (".png", ".pdf", ".svg")
# velab.fitting.results.SELECTIONS and velab.friction's laws, named here for the same reason
SELECTIONS = ("ar1", "white")
STEADY_LAWS = ("quadratic", "linear", "none")
UNSTEADY_LAWS = ("none", "vardy-brown", "brunone")


def register(sub) -> None:
    p = sub.add_parser(
        "fit",
        help="calibrate the pipe-wall models (EL, S1..S6) on run files and rank them by AIC",
        description="Calibrate the wave speed and the Kelvin-Voigt elements of EL and S1..S6 on the head "
        "record after the trigger, compare the models by AIC, and store the result in the run under "
        "/entry/fits (the recorded data are never rewritten). See docs/fitting.md.",
    )
    p.add_argument("runs", nargs="+", metavar="RUN.h5", help="run file(s)")
    p.add_argument("--models", default="0-6", help="models by number of KV elements, e.g. 0-6, 1-5, 1,3 (0 = EL; default 0-6)")
    p.add_argument("--window", type=float_range(0, 3600, lo_open=True, units="s"), default=20.0,
                   help="window after the trigger, s (default 20)")
    p.add_argument("--method", default="auto", metavar="METHOD",
                   help=f"search method: {METHOD_NAMES} (default auto: multi-start least squares, coarse-to-fine)")
    p.add_argument("--reduced", action="store_true", help="also fit the reduced S1r..S5r (tau fixed at 0.01..100 s)")
    p.add_argument("--starts", type=int_range(1, 1000), default=None,
                   help="cap on the number of starts per model (default: all)")
    p.add_argument("--no-polish", action="store_true", help="skip the full-band polish (quick look only)")
    p.add_argument("--tau-min", type=float_range(0, None, lo_open=True, units="s"), default=None, metavar="S",
                   help="shortest retardation time calibrated, s (default: the rig's [fit] table, else "
                   "max(2 sampling steps, closure time / 10))")
    p.add_argument("--tau-max", type=float_range(0, None, lo_open=True, units="s"), default=None, metavar="S",
                   help="longest retardation time calibrated, s (default: the rig's [fit] table, else 10 x window)")
    p.add_argument("--selection", choices=SELECTIONS, default="ar1",
                   help="model choice: ar1 (default; AIC of an AR(1) likelihood of the residuals, robust to "
                   "correlated residuals) or white (the paper's AIC)")
    p.add_argument("--friction", choices=STEADY_LAWS, default=None,
                   help="steady friction law of the calibration model (default: the rig's)")
    p.add_argument("--friction-unsteady", choices=UNSTEADY_LAWS, default=None,
                   help="unsteady friction law of the calibration model (default: the rig's)")
    p.add_argument("--manoeuvre", choices=("auto", "fitted", "rig"), default="auto",
                   help="the flow at the valve that drives the model: auto (default; from the recorded valve "
                   "position through the rig's valve, else a closure fitted with the wall), fitted (the closure "
                   "even with a position record), rig (the rig's sigmoid imposed as the flow: the paper's model)")
    add_json_option(p)
    p.add_argument("--plot", metavar="FILE", help="write report figures (.png, .pdf or .svg); with several runs, "
                   "one file per run named FILE-stem_RUN-stem.suffix")
    p.add_argument("--name", default=None, help="fit group name under /entry/fits: 1-64 letters, digits, _ . + - "
                   "(default: from method and window)")
    p.add_argument("--no-save", action="store_true", help="do not write the fit into the run file")
    p.add_argument("--joint", action="store_true",
                   help="calibrate ONE wall on all the runs together (runs of one pipe: a campaign): each run keeps "
                   "its steady state, manoeuvre, friction at its Q0 and noise; the fit is saved into every run, naming "
                   "the others (docs/fitting.md, 'Joint fits'); takes --method, --reduced, --starts and --no-polish")
    p.add_argument("--jobs", type=int_range(1, 256), default=1, help="runs fitted in parallel (processes; default 1)")
    p.add_argument("--scheduler", type=scheduler_address, default=None, metavar="ADDRESS",
                   help="fit the runs on a Dask cluster, e.g. tcp://10.0.0.5:8786 (needs the velab[cluster] extra; "
                   "the runs on storage every worker mounts at the same path; this client writes the fits; "
                   "docs/cluster.md)")
    p.set_defaults(func=run)



def _options(args) -> dict:
    from velab.fitting.sweep import METHODS, parse_models

    if args.method not in METHODS:
        raise DataError(f"--method {args.method!r}: choose from {', '.join(METHODS)}")
    if args.plot:
        check_output_path(args.plot, PLOT_SUFFIXES, "--plot figure")
    if args.name is not None:  # before fitting: --name can only name a fit group, never a path
        from velab.runfiles.fits import validate_fit_name

        validate_fit_name(args.name)
    if args.tau_min is not None and args.tau_max is not None and not args.tau_min < args.tau_max:
        raise DataError(f"--tau-min {args.tau_min:g} must be below --tau-max {args.tau_max:g}")
    return {
        "models": parse_models(args.models), "window_s": args.window, "method": args.method,
        "reduced": args.reduced, "starts": args.starts, "polish": not args.no_polish,
        "save": not args.no_save, "name": args.name, "plot": args.plot,
        "tau_min_s": args.tau_min, "tau_max_s": args.tau_max, "selection": args.selection,
        "friction": args.friction, "friction_unsteady": args.friction_unsteady, "manoeuvre": args.manoeuvre,
    }


def _window_position(run, t):
    """The recorded valve position on the fit window's grid t (s from the trigger), or None."""
    import numpy as np

    pos = run.channels.get("valve_position")
    if pos is None:
        return None
    return np.interp(np.asarray(t) + run.trigger_time_s, run.time_s, pos)


def _plot_path(template: str, run_path: str, many: bool) -> str:
    if not many:
        return template
    t = Path(template)
    return str(t.with_name(f"{t.stem}_{Path(run_path).stem}{t.suffix}"))


def fit_options(opts: dict):
    """``velab fit``'s options as the fitter's FitOptions (the one mapping of the command's options)."""
    from velab.fitting.options import FitOptions

    return FitOptions(models=tuple(opts["models"]), method=opts["method"], reduced=opts["reduced"],
                      starts=opts["starts"], polish=opts["polish"], tau_min_s=opts["tau_min_s"],
                      tau_max_s=opts["tau_max_s"], selection=opts["selection"], friction=opts["friction"],
                      friction_unsteady=opts["friction_unsteady"], manoeuvre=opts.get("manoeuvre", "auto"))


def fit_request(path: str, opts: dict):
    """The fit service's request (velab.fitservice) for one run file with ``velab fit``'s options: the run is
    refused before its fit when the fit is to be saved into it and cannot be (open for writing, damaged)."""
    from velab.fitservice.request import FitRequest, RunFile

    return FitRequest(RunFile(path, will_save=bool(opts["save"])), opts["window_s"], fit_options(opts),
                      label=Path(path).name)


def fit_file(path: str, opts: dict, many: bool = False, progress=None):
    """Fit one run file in this process (the fit service's in-process call, velab.fitservice.execute);
    returns (SweepResult, fit group name or None). Raises VelabError."""
    from velab.fitservice.execute import execute
    from velab.runfiles.fits import save_fit
    from velab.runfiles import RunStillOpen

    result = execute(fit_request(path, opts), progress)
    for note in result.notes:
        if note.endswith("nothing written into it"):  # (velab.fitservice.execute.save_note)
            print(f"velab: {path}: {note}", file=sys.stderr)
    name = None
    if opts["save"]:
        try:
            name = save_fit(path, result, opts["name"])
        except RunStillOpen as exc:
            # an incomplete run can be fitted (that is the point) but not written to
            result.notes.append(f"not saved: {exc}")
        except OSError as exc:
            raise DataError(f"{path}: cannot write the fit into the run: {exc}") from None
    if opts["plot"]:
        write_plot(path, result, opts, many)
    return result, name


def write_plot(path: str, result, opts: dict, many: bool) -> None:
    """The report figure of ``result`` on the run at ``path`` (``--plot``; one per run when ``many``)."""
    from velab.fitting.plots import report_figure
    from velab.runfiles import read_run

    run = read_run(path)
    figure = _plot_path(opts["plot"], path, many)
    t, h = run.fit_window(opts["window_s"])
    try:
        report_figure(t, h, run.rig, result, figure, position_pct=_window_position(run, t), run=run)
    except OSError as exc:
        raise DataError(f"{figure}: cannot write the figure: {exc.strerror or exc}") from None


def _start_walker(args) -> None:
    """Start the child that walks the run files before they are read (velab.runfiles.probe) now, when this
    process reads them (one run, a joint fit, a batch fitted here): its start-up, importing h5py (~0.3 s), then
    runs on another core while this process imports the fitter (_options), instead of being waited for at the
    first read. Runs fitted in fit processes or on a cluster are walked there."""
    from velab.batch.local import processes_for

    if args.scheduler or not (getattr(args, "joint", False) or processes_for(args.jobs, len(args.runs)) == 1):
        return
    from velab.runfiles.probe import start_walker

    start_walker(args.runs)


def run(args: argparse.Namespace) -> int:
    _start_walker(args)  # before the fitter's imports: the walker starts beside them
    opts = _options(args)
    if getattr(args, "joint", False):
        return _run_joint(args, opts)
    if len(args.runs) == 1 and not args.scheduler:
        path = args.runs[0]
        with ProgressLine.for_args(args) as progress:
            def cb(done, total, name):
                progress.update(f"velab fit {Path(path).name}: {done}/{total} models, fitted {name}")

            result, name = fit_file(path, opts, progress=cb)
        if args.json:
            write_json({"path": path, "fit_name": name, **result.to_dict(), "headline": _headline(result)})
        else:
            print(f"{path}")
            from velab.fitting.report import format_report  # (the fitter's package: only when a fit is reported)
            print(format_report(result, verbose=bool(getattr(args, "verbose", 0))))
            if name:
                print(f"saved as /entry/fits/{name}")
        return ExitCode.OK
    return _run_batch(args, opts)


def _headline(result) -> dict:
    """The report's summary as plain data (velab.fitting.headline): the JSON's "headline" object."""
    from velab.fitting.headline import headline

    return headline(result).to_dict()


def _run_batch(args, opts: dict) -> int:
    """Many runs, or any run on a cluster: velab.batch through the fit service (table, failures, exit code)."""
    from velab.batch import report
    from velab.batch.runner import run_batch

    with ProgressLine.for_args(args) as progress:
        plot = (lambda path, result: write_plot(path, result, opts, True)) if opts["plot"] else None
        batch = run_batch(fit_request, args.runs, opts, jobs=args.jobs, scheduler=args.scheduler, progress=progress,
                          plot=plot)
    if args.json:
        write_json(report.json_doc(batch))
    else:
        print(report.table(batch))
    report.print_failures(batch)
    return report.exit_code(batch)


# options of a single fit that a joint fit does not take (--method, --reduced, --starts and --no-polish it does: the
# stacked search takes them as a single fit's, velab.fitting.joint.search_options)
_NOT_JOINT = (("scheduler", "--scheduler", ""),)


def _joint_sources(args, window_s):
    """The options a joint fit refuses, then its runs read and checked (velab.jointfiles.read_sources)."""
    from velab.jointfiles import read_sources

    if len(args.runs) < 2:
        raise DataError("--joint needs two or more runs")
    for key, option, why in _NOT_JOINT:
        if getattr(args, key, None):
            raise DataError(f"{option} does not apply to a joint fit (--joint{why})")
    if args.jobs != 1:
        raise DataError("--jobs does not apply to a joint fit (--joint: one fit over all the runs)")
    return read_sources(args.runs, window_s)


def _run_joint(args, opts: dict) -> int:
    """velab fit RUN1 RUN2 ... --joint: one wall over all the runs (velab.fitting.joint), the fit service's
    in-process call (velab.fitservice.execute) as every fit."""
    from velab.fitservice.execute import execute
    from velab.fitservice.request import FitRequest, RunFiles
    from velab.fitting.jointresult import runs_report
    from velab.jointfiles import default_name, save_joint
    from velab.runfiles.fits import validate_fit_name

    sources = _joint_sources(args, opts["window_s"])
    if opts["save"] and opts["name"]:
        validate_fit_name(opts["name"])  # a bad name is said before the fit, not after it
    with ProgressLine.for_args(args) as progress:
        def cb(done, total, name):
            progress.update(f"velab fit --joint ({len(sources)} runs): {done}/{total} models, fitted {name}")

        request = FitRequest(RunFiles(tuple(s.path for s in sources)), opts["window_s"], fit_options(opts),
                             label="joint")
        result = execute(request, cb, sources=sources)  # the runs read once: fitted, saved and drawn
    name = None
    if opts["save"]:
        name = opts["name"] or default_name(opts["window_s"], opts["reduced"])
        save_joint(result, sources, name)  # into every run, naming the others
    if opts["plot"]:
        from velab.fitting.campaign import campaign_figure

        try:
            campaign_figure(result, opts["plot"], sources)
        except OSError as exc:
            raise DataError(f"{opts['plot']}: cannot write the figure: {exc.strerror or exc}") from None
    if args.json:
        write_json({"paths": [s.path for s in sources], "fit_name": name, **result.to_dict(),
                    "headline": _headline(result)})
    else:
        print("joint fit of " + ", ".join(s.path for s in sources))
        from velab.fitting.report import format_report  # (the fitter's package: only when a fit is reported)
        print(format_report(result, verbose=bool(getattr(args, "verbose", 0))))
        print(runs_report(result))
        if name:
            print(f"saved as /entry/fits/{name} in each of the {len(sources)} runs")
    return ExitCode.OK
