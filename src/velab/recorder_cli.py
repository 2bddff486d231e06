"""``velab record``: run a water-hammer test headless, stream it into HDF5, fit it online.

Exit codes (docs/recording.md): 0 completed; 2 bad arguments or configuration;
3 refused by the interlock or the readiness checks (nothing moved); 4 aborted
(pressure ceiling, valve fault, operator); 5 device or storage failure;
130 stopped by Ctrl-C / SIGTERM. For a campaign the worst run decides.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time
from pathlib import Path

from velab.commands.common import non_negative_float, positive_float
from velab.errors import VelabError

_SEVERITY = {0: 0, 3: 1, 130: 2, 4: 3, 5: 4, 2: 5}


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "record",
        help="run a water-hammer test: record into HDF5 and fit Sm models online",
        description="Connect the bench (or start the simulated rig), check readiness and the surge interlock, "
                    "record a baseline, trigger the valve manoeuvre, stream everything into an HDF5 run file "
                    "and calibrate EL..S6 by AIC as soon as the fit window is in.",
        epilog="exit codes: 0 completed, 2 bad arguments/config, 3 refused (interlock/readiness), 4 aborted, "
               "5 device or storage failure, 130 stopped (Ctrl-C/SIGTERM)",
    )
    src = p.add_mutually_exclusive_group()
    src.add_argument("--config", metavar="BENCH", help="bench config (configs/benches/<name>.toml or a path)")
    src.add_argument("--simulate", action="store_true", help="start the simulated rig in-process (zero set-up)")
    p.add_argument("--sim-config", default="default", metavar="NAME", help="sim config for --simulate (default: default)")
    p.add_argument("--material", default=None, metavar="NAME", help="simulated pipe-wall material (e.g. A, B, hdpe_s1)")
    clk = p.add_mutually_exclusive_group()
    clk.add_argument("--realtime", dest="clock", action="store_const", const="realtime",
                     help="simulated clock runs in real time (default)")
    clk.add_argument("--fast", dest="clock", action="store_const", const="fast",
                     help="simulated clock runs 12x faster than real time")
    clk.add_argument("--clock", dest="clock", metavar="KIND", help="realtime | fast | scaled:K")
    p.add_argument("--rig", default=None, help="rig config (default: the simulator's rig, or perugia)")
    p.add_argument("--duration", type=positive_float, default=30.0, help="seconds recorded after the trigger (30)")
    p.add_argument("--pretrigger", type=positive_float, default=2.0, help="baseline before the trigger, s (2)")
    p.add_argument("--rate", type=positive_float, default=1000.0, help="pressure sample rate, Hz (1000)")
    p.add_argument("--beta", type=positive_float, default=None, help="manoeuvre beta, 1/s (default: the rig's)")
    p.add_argument("--gamma", type=float, default=None, help="manoeuvre gamma (default: the rig's)")
    p.add_argument("--end-position", type=non_negative_float, default=0.0, help="final valve opening, %% (0)")
    p.add_argument("--surge-margin", type=non_negative_float, default=0.1, help="interlock margin on the surge (0.1)")
    p.add_argument("--ceiling", type=positive_float, default=None, metavar="M",
                   help="pressure ceiling, m of head (default: 95%% of the limiting pressure)")
    p.add_argument("--out-dir", default=None, help="output directory (default ./runs, created if missing)")
    p.add_argument("--title", default="")
    p.add_argument("--operator", default="")
    p.add_argument("--specimen", default="")
    p.add_argument("--notes", default="")
    p.add_argument("--repeat", type=int, default=1, metavar="N", help="campaign: N runs (1)")
    p.add_argument("--interval", type=non_negative_float, default=0.0, metavar="S", help="pause between runs, s")
    p.add_argument("--json", action="store_true", help="print a machine-readable summary (JSON) on stdout")
    p.add_argument("--no-fit", action="store_true", help="record only")
    p.add_argument("--models", default="0-6", help="models to fit, e.g. 0-6 or 1,3,5 (0 = EL)")
    p.add_argument("--window", type=positive_float, default=20.0, help="fit window after the trigger, s (20)")
    p.add_argument("--method", default="auto", help="fit method (auto, least-squares, nelder-mead, evolution)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run_command)


class _Terminate(BaseException):
    pass


def _progress(rec, out, json_mode: bool, quiet: bool):
    """A thread printing the recorder's events: rich live status on a TTY, plain lines otherwise."""
    stream = sys.stderr if json_mode else sys.stdout
    tty = stream.isatty() and not quiet
    stop = threading.Event()
    state = {"phase": "idle", "samples": 0, "lost": 0, "peak": float("-inf"), "t0": time.monotonic(), "t": 0.0}

    def line(text: str) -> None:
        if not quiet:
            print(text, file=stream, flush=True)

    def handle(ev) -> None:
        k = ev.kind
        if k == "samples":
            d = ev.data
            state["samples"] += d["time_s"].size
            state["lost"] += d["lost"]
            state["t"] = float(d["time_s"][-1])
            if d["head_m"].size:
                import numpy as np

                with np.errstate(invalid="ignore"):
                    m = np.nanmax(d["head_m"])
                if m == m:
                    state["peak"] = max(state["peak"], float(m))
        elif k == "phase":
            state["phase"] = ev.data["phase"]
            if not tty:
                extra = ev.data.get("path") or ev.data.get("reason") or ""
                line(f"[{time.monotonic() - state['t0']:7.2f} s] phase {ev.data['phase']}" + (f": {extra}" if extra else ""))
        elif k in ("message", "fault"):
            line(("warning: " if k == "fault" else "") + str(ev.data))
        elif k == "fit" and not tty:
            r = ev.data["result"]
            tag = "final" if ev.data["final"] else "intermediate"
            line(f"fit ({tag}, {ev.data['window_s']:g} s window): best {r.best.name}, a = {r.best.wave_speed_m_s:.2f} m/s")

    def loop() -> None:
        import queue as _q

        live = None
        if tty:
            try:
                from rich.live import Live
                from rich.text import Text

                live = Live(Text(""), refresh_per_second=8, console=None, transient=True)
                live.start()
            except Exception:  # noqa: BLE001
                live = None
        try:
            while not stop.is_set() or not rec.events.empty():
                try:
                    ev = rec.events.get(timeout=0.1)
                except _q.Empty:
                    ev = None
                if ev is not None:
                    handle(ev)
                if live is not None:
                    from rich.text import Text

                    live.update(Text(
                        f"{state['phase']:<10} elapsed {time.monotonic() - state['t0']:6.1f} s  t = {state['t']:7.3f} s  "
                        f"samples {state['samples']:>9}  lost {state['lost']:>5}  peak head "
                        + (f"{state['peak']:.2f} m" if state["peak"] > -1e300 else "-")))
        finally:
            if live is not None:
                live.stop()

    th = threading.Thread(target=loop, daemon=True, name="velab-record-progress")
    th.start()
    return stop, th


def _settings_from_args(args, run_number: int):
    from velab.fitting import parse_models
    from velab.recorder import RecordSettings

    out = Path(args.out_dir) if args.out_dir else Path("runs")
    if args.out_dir is None:
        out.mkdir(exist_ok=True)
    models = tuple(parse_models(args.models))
    return RecordSettings(
        duration_s=args.duration, pretrigger_s=args.pretrigger, sample_rate_hz=args.rate,
        beta_per_s=args.beta, gamma=args.gamma, end_position_pct=args.end_position, out_dir=out,
        title=args.title, operator=args.operator, specimen=args.specimen, notes=args.notes,
        fit=not args.no_fit, fit_models=models, fit_window_s=args.window, fit_method=args.method,
        surge_margin=args.surge_margin, ceiling_head_m=args.ceiling, run_number=run_number,
    )


def _make_recorder(args, settings):
    from velab.config import load_rig
    from velab.recorder import Recorder

    if args.simulate or not args.config:
        if not args.simulate and not args.config:
            raise VelabError("give --config BENCH.toml or --simulate")
        rig = load_rig(args.rig) if args.rig else None
        return Recorder.simulated(settings, sim_config=args.sim_config, material=args.material,
                                  clock=args.clock or "realtime", rig=rig)
    from velab.drivers.base import ProfileError
    from velab.drivers.bench import load_bench

    try:
        bench = load_bench(args.config)
    except ProfileError as exc:
        raise VelabError(str(exc)) from None
    if bench.simulate and args.clock:
        raise VelabError("--realtime/--fast only apply to --simulate")
    rig = load_rig(args.rig or "perugia")
    return Recorder(bench, rig, settings)


def _print_summary(summary, out) -> None:
    print(f"run: {summary.path}", file=out)
    print(f"status: {summary.status}" + (f" ({summary.reason})" if summary.reason else ""), file=out)
    print(f"samples: {summary.n_samples}, lost {summary.lost_samples} in {summary.gaps} gaps, "
          f"peak head {summary.peak_head_m:.2f} m", file=out)
    if summary.fit is not None:
        print(summary.fit.report(elements=False), file=out)
        print(f"best model: {summary.best_model}, a = {summary.wave_speed_m_s:.2f} m/s"
              + (f" (final fit {summary.fit_latency_s:.2f} s after the window closed)" if summary.fit_latency_s else ""),
              file=out)
    elif summary.fit_error:
        print(summary.fit_error, file=out)


def run_command(args) -> int:
    from velab.recorder import DeviceFailure, RunSummary

    if args.repeat < 1:
        raise VelabError("--repeat must be at least 1")
    if args.method not in ("auto", "least-squares", "nelder-mead", "evolution"):
        raise VelabError(f"unknown fit method {args.method!r}")
    settings = _settings_from_args(args, 1)
    out = sys.stderr if args.json else sys.stdout

    def on_term(signum, frame):
        raise _Terminate()

    old = signal.signal(signal.SIGTERM, on_term)
    summaries: list[RunSummary] = []
    codes: list[int] = []
    rec = None
    stopper = None
    try:
        rec = _make_recorder(args, settings)
        stopper = _progress(rec, out, args.json, args.quiet)
        for i in range(args.repeat):
            if i:
                rec.settings = settings.with_changes(run_number=i + 1)
                if args.interval:
                    time.sleep(args.interval)
            try:
                try:
                    s = rec.run(reset_valve=i > 0)
                except (KeyboardInterrupt, _Terminate):
                    s = _interrupt(rec)
            except DeviceFailure as exc:
                print(f"velab: {exc}", file=sys.stderr)
                codes.append(exc.exit_code)
                break
            except VelabError as exc:
                print(f"velab: {exc}", file=sys.stderr)
                codes.append(exc.exit_code)
                break
            summaries.append(s)
            codes.append(s.exit_code)
            time.sleep(0.05)
            if not args.quiet:
                _print_summary(s, out)
            if s.exit_code == 130:
                break
    except (KeyboardInterrupt, _Terminate):
        codes.append(130)
    finally:
        if stopper is not None:
            stopper[0].set()
            stopper[1].join(2.0)
        if rec is not None:
            try:
                rec.close()
            except (KeyboardInterrupt, _Terminate):
                pass
        signal.signal(signal.SIGTERM, old)
    code = max(codes, key=lambda c: _SEVERITY.get(c, 4)) if codes else 0
    if args.repeat > 1 and not args.quiet:
        print(f"campaign: {len(summaries)} of {args.repeat} runs, "
              + ", ".join(f"{s.path.name if s.path else '-'}: {s.status} {s.best_model or ''}".rstrip() for s in summaries),
              file=out)
    if args.json:
        doc = {"exit_code": code, "runs": [s.to_dict() for s in summaries]}
        if args.repeat > 1:
            best = [s.best_model for s in summaries if s.best_model]
            a = [s.wave_speed_m_s for s in summaries if s.wave_speed_m_s]
            doc["campaign"] = {"runs": len(summaries), "requested": args.repeat,
                               "statuses": [s.status for s in summaries],
                               "best_models": best,
                               "wave_speed_mean_m_s": (sum(a) / len(a)) if a else None}
        json.dump(doc, sys.stdout, indent=1, default=str)
        print()
    return code


def _interrupt(rec):
    """Ctrl-C / SIGTERM during a run: stop cleanly (actuator safe, file "stopped"), keep the data."""
    print("velab: stopping (Ctrl-C/SIGTERM): actuator to its safe state, closing the run file", file=sys.stderr)
    while True:
        try:
            rec.stop().result(timeout=30)
            summary = rec.wait(120)
            break
        except (KeyboardInterrupt, _Terminate):
            continue  # a second Ctrl-C does not leave the file open
    summary.status = "stopped" if summary.status in ("completed", "stopped") else summary.status
    return summary
