"""``velab record``: run a water-hammer test headless, stream it into HDF5, fit it online.

Exit codes (docs/recording.md): 0 completed; 2 bad arguments or configuration;
3 refused by the interlock or the readiness checks (nothing moved); 4 aborted
(pressure ceiling, valve fault, armed timeout, operator); 5 device or storage failure;
6 completed with faults (data flagged); 130 stopped by Ctrl-C / SIGTERM. For a campaign
the worst run decides. Progress goes to stderr; the summary to stdout (JSON with --json).
"""

from __future__ import annotations

import math
import queue
import shutil
import signal
import sys
import threading
import time
from pathlib import Path

from velab import bounds
from velab.configpath import DEFAULT_SIM
from velab.commands.common import add_json_option, bound_float, float_range, int_range, write_json
from velab.errors import DataError, VelabError

# the recorder's own floor: a baseline shorter than this gives no steady head (velab.recording.settings)
MIN_PRETRIGGER_S = 0.05


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "record",
        help="run a water-hammer test: record into HDF5 and fit Sm models online",
        description="Connect the bench (or start the simulated rig), check readiness and the surge interlock, "
                    "record a baseline, trigger the valve manoeuvre, stream everything into an HDF5 run file "
                    "and calibrate EL..S6 by AIC as soon as the fit window is in.",
        epilog="exit codes: 0 completed, 2 bad arguments/config, 3 refused (interlock/readiness), 4 aborted, "
               "5 device or storage failure, 6 completed with faults (data flagged), 130 stopped (Ctrl-C/SIGTERM)",
    )
    src = p.add_mutually_exclusive_group()
    src.add_argument("--config", metavar="BENCH", help="bench config (configs/benches/<name>.toml or a path)")
    src.add_argument("--simulate", action="store_true", help="start the simulated rig in-process (zero set-up)")
    p.add_argument("--sim-config", default=DEFAULT_SIM, metavar="NAME",
                   help=f"sim config for --simulate (default: {DEFAULT_SIM}: a DATAQ DI-2108 and a valve fired by its "
                        "digital line; 'default': velab's own SADC-4, Modbus ADC and servo actuator)")
    p.add_argument("--material", default=None, metavar="NAME", help="simulated pipe-wall material (e.g. A, B, hdpe_s1)")
    clk = p.add_mutually_exclusive_group()
    clk.add_argument("--realtime", dest="clock", action="store_const", const="realtime",
                     help="simulated clock runs in real time (default)")
    clk.add_argument("--fast", dest="clock", action="store_const", const="fast",
                     help="simulated clock runs 12x faster than real time")
    clk.add_argument("--clock", dest="clock", metavar="KIND", help="realtime | fast | scaled:K")
    p.add_argument("--rig", default=None, help="rig config (with --simulate: the rig simulated; default: the "
                                               "sim config's rig, or perugia)")
    # the bounds of `velab synth` (velab.bounds): what is physical is said once, whatever the door
    p.add_argument("--duration", type=float_range(0, 3600, lo_open=True, units="s"), default=30.0,
                   help="seconds recorded after the trigger (30)")
    p.add_argument("--pretrigger", type=float_range(MIN_PRETRIGGER_S, 600, units="s"), default=2.0,
                   help="baseline before the trigger, s (2)")
    p.add_argument("--rate", "--sample-rate", dest="rate", type=bound_float(bounds.SAMPLE_RATE_HZ), default=1000.0,
                   help="pressure sample rate, Hz (1000; within the pressure source's range)")
    p.add_argument("--beta", type=bound_float(bounds.BETA_PER_S), default=None,
                   help="manoeuvre beta, 1/s (default: the rig's)")
    p.add_argument("--gamma", type=bound_float(bounds.GAMMA), default=None,
                   help="manoeuvre gamma, -100..0 (default: the rig's)")
    p.add_argument("--end-position", type=float_range(0, 100, hi_open=True, units="%"), default=0.0, help="final valve opening, %% (0)")
    p.add_argument("--surge-margin", type=float_range(0, 10), default=0.1, help="interlock margin on the surge (0.1)")
    p.add_argument("--ceiling", type=float_range(0, bounds.HEAD_M.hi, lo_open=True, units="m"), default=None,
                   metavar="M",
                   help="pressure ceiling, m of head (default: 95%% of the limiting pressure; never above it)")
    p.add_argument("--armed-timeout", type=float_range(0, 86400, lo_open=True, units="s"), default=None, metavar="S",
                   help="disarm an armed rig left without a trigger after S s (default: the bench's "
                        "[recorder] armed_timeout_s, else 300)")
    p.add_argument("--reopen-valve", action="store_true",
                   help="reopen the valve (actuator reset) before the first run, e.g. after a previous run closed it")
    p.add_argument("--out-dir", default=None, help="output directory (default ./runs, created if missing)")
    p.add_argument("--title", default="")
    p.add_argument("--operator", default="")
    p.add_argument("--specimen", default="")
    p.add_argument("--notes", default="")
    p.add_argument("--repeat", type=int_range(1, 10000), default=1, metavar="N",
                   help="campaign: N runs, the valve reopened and the steady state re-checked between runs (1)")
    p.add_argument("--interval", type=float_range(0, 86400, units="s"), default=0.0, metavar="S", help="pause between runs, s (0)")
    add_json_option(p)
    p.add_argument("--no-fit", action="store_true", help="record only")
    p.add_argument("--models", default="0-6", help="models to fit, e.g. 0-6 or 1,3,5 (0 = EL)")
    p.add_argument("--window", type=float_range(0, 3600, lo_open=True, units="s"), default=20.0,
                   help="fit window after the trigger, s (20)")
    p.add_argument("--method", default="auto", help="fit method (auto, least-squares, nelder-mead, evolution)")
    p.set_defaults(func=run_command)


class _Terminate(BaseException):
    pass


def status_line(state: dict, width: int = 79) -> str:
    """The live status line: phase, countdown, t, peak head, samples and lost, never wider than ``width``.

    The peak head is never cut: where the line does not fit, the samples count goes first, then the
    words around the numbers, then the countdown (an 80-column terminal: width 79)."""
    peak = f"{state['peak']:.2f} m" if state["peak"] > -1e300 else "-"
    phase, cd = state["phase"], state.get("countdown") or ""
    t, n, lost = state["t"], state["samples"], state["lost"]
    at = f"{phase} ({cd})" if cd else phase
    forms = (
        f"{phase:<12} {cd:<20} | t {t:8.3f} s | peak head {peak} | {n} samples, {lost} lost",
        f"{at} | t {t:.2f} s | peak head {peak} | {n} samples, {lost} lost",
        f"{at} | t {t:.1f} s | peak head {peak} | {lost} lost",
        f"{phase} | t {t:.1f} s | peak head {peak} | {lost} lost",
        f"{phase} | t {t:.1f} s | peak {peak}",
    )
    for i, text in enumerate(forms):
        text = text if i == 0 else " ".join(text.split())  # (no countdown: no double space)
        if len(text) <= width:
            return text
    return " ".join(forms[-1].split())[:max(10, width)]


class _Progress:
    """Prints the recorder's events (stderr) from its own thread.

    Phases (with their countdowns), messages, faults and fits are plain lines. On a terminal a
    one-line live status (phase, countdown, t, samples, lost, peak head) is kept under them, cut
    to the terminal's width and erased before anything else is printed; ``pause()`` drains the
    pending events and erases it so the run summary is printed cleanly.
    """

    def __init__(self, rec, quiet: bool):
        self.rec = rec
        self.stream = sys.stderr
        self.quiet = quiet
        self.tty = (not quiet) and self.stream.isatty()
        self.lock = threading.Lock()
        self.stop_ev = threading.Event()
        self.paused = False
        self.status_shown = False
        self.state = {"phase": "disconnected", "samples": 0, "lost": 0, "peak": float("-inf"),
                      "t0": time.monotonic(), "t": 0.0, "countdown": ""}
        self.thread = threading.Thread(target=self._loop, daemon=True, name="velab-record-progress")
        self.thread.start()

    def _erase(self) -> None:
        if self.status_shown:
            self.stream.write("\r\x1b[2K")
            self.status_shown = False

    def line(self, text: str) -> None:
        if self.quiet:
            return
        with self.lock:
            self._erase()
            print(text, file=self.stream, flush=True)

    def _status(self) -> None:
        text = status_line(self.state, shutil.get_terminal_size((80, 24)).columns - 1)
        with self.lock:
            self.stream.write("\r\x1b[2K" + text)
            self.stream.flush()
            self.status_shown = True

    def handle(self, ev) -> None:
        handler = self._HANDLERS.get(ev.kind)
        if handler is not None:
            handler(self, ev.data)

    def _on_samples(self, d) -> None:
        st = self.state
        st["samples"] += d["time_s"].size
        st["lost"] += d["lost"]
        if d["time_s"].size:
            st["t"] = float(d["time_s"][-1])
        q = d.get("quality")
        h = d["head_m"] if q is None else d["head_m"][q == 0]
        if h.size:
            import numpy as np  # (here: `velab --help` never loads numpy)

            with np.errstate(invalid="ignore"):
                m = np.nanmax(h) if np.isfinite(h).any() else float("nan")
            if m == m:
                st["peak"] = max(st["peak"], float(m))

    def _on_progress(self, d) -> None:
        left = d["remaining_s"]
        # the fit window in, the record goes on to its duration: say so, not "0.0 s" for the rest of the run
        self.state["countdown"] = (f"{d['what']} {left:.1f} s" if left > 0 or d["what"] != "fit window"
                                   else "fit window in")

    # what each phase line adds, from the phase event's data
    _PHASE_TEXT = {
        "armed": lambda d: ("trigger queued: it goes out as soon as the baseline is in" if d.get("trigger_queued") else
                            f"{d.get('path')}; recording the {d.get('baseline_s', 0):g} s baseline "
                            f"(disarms after {d.get('armed_timeout_s', 0):g} s without a trigger)"),
        "triggerable": lambda d: f"baseline in; disarms in {d.get('disarm_in_s', 0):.0f} s without a trigger",
        "recording": lambda d: (f"trigger commanded at t = {d['trigger_time_s']:.3f} s; fit window "
                                f"{d.get('fit_window_s', 0):g} s"),
        "fitting": lambda d: f"final fit (run {d.get('status')})",
        "completed": lambda d: d.get("reason") or d.get("path") or "",
        "completed-with-faults": lambda d: d.get("reason") or d.get("path") or "",
    }

    def _on_phase(self, d) -> None:
        st, phase = self.state, d["phase"]
        if phase == st["phase"] and not d.get("trigger_queued"):
            return
        st["phase"], st["countdown"] = phase, ""
        if phase == "connecting":
            st.update(samples=0, lost=0, peak=float("-inf"), t=0.0, t0=time.monotonic())
        extra = self._PHASE_TEXT.get(phase, lambda d: d.get("reason") or "")(d)
        self.line(f"[{time.monotonic() - st['t0']:7.2f} s] {phase}" + (f": {extra}" if extra else ""))

    def _on_trigger(self, d) -> None:
        if d.get("measured"):
            self.line(f"trigger measured from the valve position: t = {d['trigger_time_s']:.4f} s")

    def _on_fit(self, d) -> None:
        r = d["result"]
        tag = "final" if d["final"] else "intermediate"
        self.line(f"fit ({tag}, {d['window_s']:g} s window): best {r.best.name}, a = {r.best.wave_speed_m_s:.2f} m/s")

    # each engine event kind (velab.recording.types.RecorderEvent) -> its line or status update
    _HANDLERS = {
        "samples": _on_samples,
        "progress": _on_progress,
        "phase": _on_phase,
        "trigger": _on_trigger,
        "message": lambda self, d: self.line(str(d)),
        "fault": lambda self, d: self.line(f"warning: {d}"),
        "fit": _on_fit,
    }

    def _loop(self) -> None:
        last = 0.0
        while not self.stop_ev.is_set():
            try:
                ev = self.rec.events.get(timeout=0.1)
            except queue.Empty:
                ev = None
            if ev is not None:
                self.handle(ev)
                if ev.kind == "done":
                    self.paused = True
            if self.tty and not self.paused and time.monotonic() - last > 0.125:
                last = time.monotonic()
                self._status()

    def pause(self, timeout: float = 2.0) -> None:
        """Before printing a summary: handle the events already queued, erase the status line."""
        deadline = time.monotonic() + timeout
        while not self.rec.events.empty() and time.monotonic() < deadline:
            time.sleep(0.01)
        self.paused = True
        with self.lock:
            self._erase()
            self.stream.flush()

    def resume(self) -> None:
        self.paused = False

    def close(self) -> None:
        self.pause()
        self.stop_ev.set()
        self.thread.join(2.0)
        with self.lock:
            self._erase()


def _out_dir(args) -> Path:
    out = Path(args.out_dir) if args.out_dir else Path("runs")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise VelabError(f"--out-dir {out}: cannot create the output directory ({exc.strerror or exc})") from None
    if not out.is_dir():
        raise VelabError(f"--out-dir {out}: not a directory")
    return out


def check_arguments(args) -> None:
    """What the options say together, by velab.bounds, before anything is created or connected: the record's
    samples (rate x (pretrigger + duration)) and, when both are given, the manoeuvre's half closure. A value
    outside is one line (DataError, exit 2). Each option alone is checked by its argparse type."""
    samples = args.rate * (args.pretrigger + args.duration)
    if samples > bounds.MAX_SAMPLES:
        raise DataError(f"--rate {args.rate:g} Hz x (--pretrigger {args.pretrigger:g} s + --duration "
                        f"{args.duration:g} s) is {samples:.3g} samples, more than the "
                        f"{bounds.MAX_SAMPLES:,} of one record: lower --rate or shorten --duration")
    if args.beta is not None and args.gamma is not None:
        half = -args.gamma / args.beta
        reason = bounds.HALF_CLOSURE_S(half)
        if reason:
            raise DataError(f"--gamma {args.gamma:g} with --beta {args.beta:g}: half closure {half:.3g} s: {reason}")


def _settings_from_args(args, run_number: int):
    from velab.fitting import parse_models
    from velab.recording import RecordSettings

    return RecordSettings(
        duration_s=args.duration, pretrigger_s=args.pretrigger, sample_rate_hz=args.rate,
        beta_per_s=args.beta, gamma=args.gamma, end_position_pct=args.end_position, out_dir=_out_dir(args),
        title=args.title, operator=args.operator, specimen=args.specimen, notes=args.notes,
        fit=not args.no_fit, fit_models=tuple(parse_models(args.models)), fit_window_s=args.window,
        fit_method=args.method, surge_margin=args.surge_margin, ceiling_head_m=args.ceiling, run_number=run_number,
        armed_timeout_s=args.armed_timeout,
    )


def make_recorder(args, settings):
    """The Recorder for ``--simulate`` (in-process rig) or ``--config BENCH`` (shared with ``velab valve``)."""
    from velab.config import load_rig
    from velab.recording import Recorder

    if getattr(args, "simulate", False) or not args.config:
        if not getattr(args, "simulate", False):
            raise VelabError("give --config BENCH.toml or --simulate")
        if args.rig:
            load_rig(args.rig)  # a bad rig file is the rig's one-line error, before any simulator starts
        # the simulated rig is the rig named (its geometry, valve, friction): what the recorder checks against
        return Recorder.simulated(settings, sim_config=args.sim_config, material=args.material,
                                  clock=args.clock or "realtime", rig=args.rig)
    from velab.drivers.base import ProfileError
    from velab.drivers.bench import load_bench

    try:
        bench = load_bench(args.config)
    except ProfileError as exc:
        raise VelabError(str(exc)) from None
    if getattr(args, "clock", None):
        raise VelabError("--realtime/--fast/--clock only apply to --simulate")
    rig = load_rig(args.rig or "perugia")
    return Recorder(bench, rig, settings)


def _print_summary(summary, out, verbose: bool = False) -> None:
    """The run's result first (velab.fitting.headline), then the run's facts, then the models' table
    (every statistic with ``verbose``); no line wider than 100 columns unless ``verbose``."""
    print("", file=out)
    if summary.fit is not None:
        from velab.fitting.headline import headline, headline_lines

        for line in headline_lines(headline(summary.fit)):
            print(line, file=out)
        print("", file=out)
    print(f"run: {summary.path}", file=out)
    print(f"status: {summary.status}" + (f" ({summary.reason})" if summary.reason else ""), file=out)
    peak = f"{summary.peak_head_m:.2f} m" if math.isfinite(summary.peak_head_m) else "-"
    trig = f", trigger at t = {summary.trigger_time_s:.4f} s" if summary.trigger_time_s is not None else ""
    print(f"samples: {summary.n_samples}, lost {summary.lost_samples} in {summary.gaps} gaps, "
          f"{summary.flagged_samples} flagged, peak head {peak}{trig}", file=out)
    if summary.fit is not None:
        from velab.fitting.report import format_report  # (the fitter's package: only when a fit is reported)
        text = format_report(summary.fit, elements=verbose, verbose=verbose)
        # (the headline is printed above the run's facts: the table and the notes follow here)
        body = text.split("\n\n", 1)[1] if "\n\n" in text else text
        print("", file=out)
        print(body.rstrip(), file=out)
        if summary.fit_latency_s:
            print(f"final fit {summary.fit_latency_s:.2f} s after the window closed", file=out)
    if summary.fit_error:
        print(summary.fit_error, file=out)


def _campaign_table(summaries, requested: int, out) -> None:
    print(f"\ncampaign: {len(summaries)} of {requested} runs", file=out)
    print(f"{'#':>3}  {'run file':<28} {'status':<22} {'best':<5} {'a (m/s)':>8} {'peak (m)':>9}", file=out)
    for i, s in enumerate(summaries, 1):
        a = f"{s.wave_speed_m_s:.2f}" if s.wave_speed_m_s else "-"
        pk = f"{s.peak_head_m:.2f}" if math.isfinite(s.peak_head_m) else "-"
        print(f"{i:>3}  {(s.path.name if s.path else '-'):<28} {s.status:<22} {s.best_model or '-':<5} {a:>8} "
              f"{pk:>9}", file=out)


def run_command(args) -> int:
    from velab.recording.phases import worst_exit_code

    if args.method not in ("auto", "least-squares", "nelder-mead", "evolution"):
        raise VelabError(f"unknown fit method {args.method!r}")
    check_arguments(args)  # before the output folder is made or any device is touched
    settings = _settings_from_args(args, 1)
    out = sys.stderr if args.json else sys.stdout

    def on_term(signum, frame):
        raise _Terminate()

    old = signal.signal(signal.SIGTERM, on_term)
    summaries, codes = [], []
    rec = progress = None
    try:
        rec = make_recorder(args, settings)
        progress = _Progress(rec, args.quiet)
        for i in range(args.repeat):
            progress.resume()
            if i:
                rec.settings = settings.with_changes(run_number=i + 1)
                if args.interval:
                    time.sleep(args.interval)
            try:
                try:
                    s = rec.run(reset_valve=i > 0 or args.reopen_valve)
                except (KeyboardInterrupt, _Terminate):
                    s = _interrupt(rec)
            except VelabError as exc:  # RunRefused (3), DeviceFailure (5), bad settings (2)
                progress.pause()
                print(f"velab: {exc}", file=sys.stderr)
                codes.append(exc.exit_code)
                break
            summaries.append(s)
            codes.append(s.exit_code)
            progress.pause()
            if not args.quiet:
                _print_summary(s, out, verbose=bool(getattr(args, "verbose", 0)))
            if s.exit_code in (130, 5):
                break
    except (KeyboardInterrupt, _Terminate):
        codes.append(130)
    finally:
        if progress is not None:
            progress.close()
        if rec is not None:
            try:
                rec.close()
            except (KeyboardInterrupt, _Terminate):
                pass
        signal.signal(signal.SIGTERM, old)
    code = worst_exit_code(codes)
    if args.repeat > 1 and not args.quiet:
        _campaign_table(summaries, args.repeat, out)
    if args.json:
        doc = {"exit_code": code, "runs": [s.to_dict() for s in summaries]}
        if args.repeat > 1:
            a = [s.wave_speed_m_s for s in summaries if s.wave_speed_m_s]
            doc["campaign"] = {"runs": len(summaries), "requested": args.repeat,
                               "statuses": [s.status for s in summaries],
                               "best_models": [s.best_model for s in summaries],
                               "wave_speed_mean_m_s": (sum(a) / len(a)) if a else None}
        write_json(doc)
    return code


def _interrupt(rec):
    """Ctrl-C / SIGTERM during a run: stop cleanly (actuator safe, file "stopped"), keep the data."""
    print("velab: stopping (Ctrl-C/SIGTERM): actuator to its safe state, closing the run file", file=sys.stderr)
    while True:
        try:
            rec.stop().result(timeout=60)
            summary = rec.wait(120)
            break
        except (KeyboardInterrupt, _Terminate):
            continue  # a second Ctrl-C does not leave the file open
    return summary
