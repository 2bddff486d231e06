"""``velab fit``: calibrate EL/Sm models on run files and rank them by AIC."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

from velab.errors import DataError, VelabError


def register(sub) -> None:
    from velab.fitting.friction import STEADY_LAWS, UNSTEADY_LAWS
    from velab.fitting.results import SELECTIONS
    from velab.fitting.sweep import METHODS

    p = sub.add_parser(
        "fit",
        help="calibrate the pipe-wall models (EL, S1..S6) on run files and rank them by AIC",
        description="Calibrate the wave speed and the Kelvin-Voigt elements of EL and S1..S6 on the head "
        "record after the trigger, compare the models by AIC, and store the result in the run under "
        "/entry/fits (the recorded data are never rewritten). See docs/fitting.md.",
    )
    p.add_argument("runs", nargs="+", metavar="RUN.h5", help="run file(s)")
    p.add_argument("--models", default="0-6", help="models by number of KV elements, e.g. 0-6, 1-5, 1,3 (0 = EL; default 0-6)")
    p.add_argument("--window", type=float, default=20.0, help="window after the trigger, s (default 20)")
    p.add_argument("--method", choices=METHODS, default="auto",
                   help="search method (default auto: multi-start least squares, coarse-to-fine)")
    p.add_argument("--reduced", action="store_true", help="also fit the reduced S1r..S5r (tau fixed at 0.01..100 s)")
    p.add_argument("--starts", type=int, default=None, help="cap on the number of starts per model (default: all)")
    p.add_argument("--no-polish", action="store_true", help="skip the full-band polish (quick look only)")
    p.add_argument("--tau-min", type=float, default=None, metavar="S",
                   help="shortest retardation time calibrated, s (default: the rig's [fit] table, else "
                   "max(2 sampling steps, closure time / 10))")
    p.add_argument("--tau-max", type=float, default=None, metavar="S",
                   help="longest retardation time calibrated, s (default: the rig's [fit] table, else 10 x window)")
    p.add_argument("--selection", choices=SELECTIONS, default="ar1",
                   help="model choice: ar1 (default; AIC of an AR(1) likelihood of the residuals, robust to "
                   "correlated residuals) or white (the paper's AIC)")
    p.add_argument("--friction", choices=STEADY_LAWS, default=None,
                   help="steady friction law of the calibration model (default: the rig's)")
    p.add_argument("--friction-unsteady", choices=UNSTEADY_LAWS, default=None,
                   help="unsteady friction law of the calibration model (default: the rig's)")
    p.add_argument("--json", action="store_true", help="print one JSON document on stdout instead of tables")
    p.add_argument("--plot", metavar="FILE", help="write report figures (.png or .pdf); with several runs, "
                   "one file per run named FILE-stem_RUN-stem.suffix")
    p.add_argument("--name", default=None, help="fit group name under /entry/fits (default: from method and window)")
    p.add_argument("--no-save", action="store_true", help="do not write the fit into the run file")
    p.add_argument("--jobs", type=int, default=1, help="runs fitted in parallel (processes; default 1)")
    p.set_defaults(func=run)


def _options(args) -> dict:
    from velab.fitting.sweep import parse_models

    if args.window is not None and not (args.window > 0 and math.isfinite(args.window)):
        raise DataError(f"--window must be a positive number of seconds, got {args.window:g}")
    if args.jobs < 1:
        raise DataError(f"--jobs must be at least 1, got {args.jobs}")
    if args.plot and Path(args.plot).suffix.lower() not in (".png", ".pdf", ".svg"):
        raise DataError(f"--plot {args.plot}: use a .png, .pdf or .svg file name")
    for opt, v in (("--tau-min", args.tau_min), ("--tau-max", args.tau_max)):
        if v is not None and not (math.isfinite(v) and v > 0):
            raise DataError(f"{opt} must be a positive number of seconds, got {v:g}")
    if args.tau_min is not None and args.tau_max is not None and not args.tau_min < args.tau_max:
        raise DataError(f"--tau-min {args.tau_min:g} must be below --tau-max {args.tau_max:g}")
    return {
        "models": parse_models(args.models), "window_s": args.window, "method": args.method,
        "reduced": args.reduced, "starts": args.starts, "polish": not args.no_polish,
        "save": not args.no_save, "name": args.name, "plot": args.plot,
        "tau_min_s": args.tau_min, "tau_max_s": args.tau_max, "selection": args.selection,
        "friction": args.friction, "friction_unsteady": args.friction_unsteady,
    }


def _plot_path(template: str, run_path: str, many: bool) -> str:
    if not many:
        return template
    t = Path(template)
    return str(t.with_name(f"{t.stem}_{Path(run_path).stem}{t.suffix}"))


def fit_file(path: str, opts: dict, many: bool = False, progress=None):
    """Fit one run file; returns (SweepResult, fit group name or None). Raises VelabError."""
    from velab.fitting.store import save_fit
    from velab.fitting.sweep import fit_sweep
    from velab.runfile import RunStillOpen, read_run

    run = read_run(path)
    t, h = run.fit_window(opts["window_s"])
    result = fit_sweep(t, h, run.rig, models=opts["models"], window_s=None, method=opts["method"],
                       reduced=opts["reduced"], starts=opts["starts"], polish=opts["polish"],
                       progress=progress, tau_min_s=opts["tau_min_s"], tau_max_s=opts["tau_max_s"],
                       selection=opts["selection"], friction=opts["friction"],
                       friction_unsteady=opts["friction_unsteady"])
    result.settings["window_s_requested"] = opts["window_s"]
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
        from velab.fitting.plots import report_figure

        report_figure(t, h, run.rig, result, _plot_path(opts["plot"], path, many))
    return result, name


def _worker(path: str, opts: dict) -> dict:
    t0 = time.perf_counter()
    try:
        result, name = fit_file(path, opts, many=True)
    except VelabError as exc:
        return {"path": path, "error": str(exc)}
    except Exception as exc:  # one bad file must not stop the others
        return {"path": path, "error": f"{path}: {type(exc).__name__}: {exc}"}
    return {"path": path, "result": result, "fit_name": name, "seconds": time.perf_counter() - t0}


def run(args: argparse.Namespace) -> int:
    opts = _options(args)
    if len(args.runs) == 1:
        path = args.runs[0]
        if args.json:
            result, name = fit_file(path, opts)
            doc = {"path": path, "fit_name": name, **result.to_dict()}
            print(json.dumps(clean_json(doc), indent=1, allow_nan=False))
        else:
            result, name = _fit_one_verbose(path, opts)
            print(f"{path}")
            print(result.report())
            if name:
                print(f"saved as /entry/fits/{name}")
        return 0
    return _run_many(args.runs, opts, args.jobs, args.json)


def _fit_one_verbose(path, opts):
    if not sys.stderr.isatty():
        return fit_file(path, opts)
    from rich.progress import Progress

    with Progress(transient=True) as prog:
        task = prog.add_task("fitting", total=None)

        def cb(done, total, name):
            prog.update(task, completed=done, total=total, description=f"fitted {name}")

        return fit_file(path, opts, progress=cb)


def clean_json(o):
    """Non-finite floats -> None, recursively (JSON has no NaN/inf)."""
    if isinstance(o, float):
        return o if math.isfinite(o) else None
    if isinstance(o, dict):
        return {k: clean_json(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [clean_json(v) for v in o]
    return o


def _run_many(paths: list[str], opts: dict, jobs: int, as_json: bool) -> int:
    outcomes: dict[str, dict] = {}
    progress = None
    if not as_json:
        try:
            from rich.progress import Progress

            from rich.console import Console

            progress = Progress(console=Console(stderr=True))
        except ImportError:  # pragma: no cover
            progress = None
    if progress is not None:
        progress.start()
        task = progress.add_task("fitting runs", total=len(paths))
    try:
        if jobs == 1:
            for p in paths:
                outcomes[p] = _worker(p, opts)
                if progress is not None:
                    progress.advance(task)
        else:
            with ProcessPoolExecutor(max_workers=min(jobs, len(paths), os.cpu_count() or 1)) as ex:
                futs = {ex.submit(_worker, p, opts): p for p in paths}
                for fut in as_completed(futs):
                    p = futs[fut]
                    try:
                        outcomes[p] = fut.result()
                    except Exception as exc:  # a crashed worker process
                        outcomes[p] = {"path": p, "error": f"{p}: worker failed: {exc}"}
                    if progress is not None:
                        progress.advance(task)
    finally:
        if progress is not None:
            progress.stop()
    failed = [o for o in outcomes.values() if "error" in o]
    if as_json:
        doc = {"runs": []}
        for p in paths:
            o = outcomes[p]
            if "error" in o:
                doc["runs"].append({"path": p, "error": o["error"]})
            else:
                doc["runs"].append({"path": p, "fit_name": o["fit_name"], **o["result"].to_dict()})
        print(json.dumps(clean_json(doc), indent=1, allow_nan=False))
    else:
        print(f"{'run':<40}{'best':>6}{'F (m^2)':>13}{'a (m/s)':>10}{'2nd':>6}{'dAIC':>8}{'time (s)':>10}")
        for p in paths:
            o = outcomes[p]
            if "error" in o:
                print(f"{Path(p).name:<40}  FAILED (see below)")
                continue
            r = o["result"]
            ranked = sorted(r.models, key=lambda f: f.aic)
            second = ranked[1] if len(ranked) > 1 else None
            print(f"{Path(p).name:<40}{r.best.name:>6}{r.best.F:>13.5e}{r.best.wave_speed_m_s:>10.2f}"
                  f"{(second.name if second else '-'):>6}{(second.delta_aic if second else math.nan):>8.2f}{o['seconds']:>10.2f}")
    for o in failed:
        print(f"velab: {o['error']}", file=sys.stderr)
    return 2 if failed else 0

