"""Online-fit latency: from the fit window closing to the final fit, at 1 kHz and 10 kHz (issue 13:
< 2 s), against the same fit run offline on the recorded file in the same run (the baseline).

Each case records material A on the simulated rig (quadratic friction) in real time, models EL..S6,
the run going on for ``--after`` seconds past the fit window (the recorder keeps acquiring at the
full rate while the fit runs, as in a normal run), then re-fits the run file with
``velab.fitting.fit_run`` (what ``velab fit`` does) and checks that the result is the online one.
The final fit is the whole fit of the window, started when it closes (a record as a stack of one part,
velab.fitting.recordfit; until the twenty-fifth round a lead fit ran on the window's first half while the
rest was recorded).
Latency = the recorder's ``fit_latency_s``; the ratio (median over runs of latency / that run's offline
fit time) says how much of the latency is the fit itself (1.0: all of it). ``--fit both`` (the default)
runs every recording twice in turn, the fit in its own process (the default setting) and in the
recorder's process (``RecordSettings.fit_process=False``), on the same machine load.

By default the simulated devices run in their own process (``velab sim --ephemeral --json``), as the
real ones are other hardware: the recorder's process holds only what it holds on a bench. ``--sim
in-process`` runs them in the recorder's process (``Recorder.simulated``, ``velab record --simulate``),
where the simulator's threads share the interpreter with the fit; ``--clock fast`` (in-process only)
runs them at 12 x real time: a quick check, not the figure (the simulated acquisition then costs 12
times the CPU it costs on a bench).

    python benchmarks/online_fit_latency.py                  # 1 and 10 kHz, 20 s window, 3 runs each
    python benchmarks/online_fit_latency.py --repeat 1 --sim in-process --clock fast
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

from velab.config import load_rig
from velab.drivers.bench import Bench
from velab.fitting import SweepResult, fit_run
from velab.recording import Recorder, RecordSettings
from velab.runfiles import read_run
from velab.runfiles.summary import read_fits


@contextlib.contextmanager
def simulator_process():
    """``velab sim`` in its own process; yields the bench that reaches its devices."""
    p = subprocess.Popen([sys.executable, "-m", "velab.cli", "sim", "--ephemeral", "--json"], stdout=subprocess.PIPE,
                         text=True)
    try:
        line = p.stdout.readline()
        if not line:
            raise SystemExit("velab sim did not start")
        yield Bench.from_dict(json.loads(line)["bench"], "velab sim --json")
    finally:
        p.terminate()
        p.wait(10)


def one(folder: str, rate: float, window_s: float, after_s: float, bench, clock: str,
        fit_process: bool = True) -> tuple[float, float, bool, str]:
    s = RecordSettings(duration_s=window_s + after_s, fit_window_s=window_s, pretrigger_s=1.5, sample_rate_hz=rate,
                       out_dir=folder, fit_process=fit_process)
    rec = Recorder.simulated(s, "default", material="A", clock=clock) if bench is None else \
        Recorder(bench, load_rig("perugia"), s)
    with rec:  # closes the devices: the simulator serves one client at a time, as the real ADC does
        summary = rec.run()
        if bench is not None:
            rec.reset_valve().result(timeout=60)  # reopened for the next run (velab valve open)
    if summary.fit is None:
        raise SystemExit(f"{rate:g} Hz: no online fit: {summary.fit_error}")
    online = SweepResult.from_dict(read_fits(summary.path)["online"])
    t0 = time.perf_counter()
    offline = fit_run(read_run(summary.path), window_s, models=list(s.fit_models), method=s.fit_method)
    t_off = time.perf_counter() - t0
    same = offline.best.name == online.best.name and all(
        a.F == b.F and a.wave_speed_m_s == b.wave_speed_m_s for a, b in zip(online.models, offline.models))
    return float(summary.fit_latency_s), t_off, same, online.best.name


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--window", type=float, default=20.0, help="fit window, s (20)")
    ap.add_argument("--after", type=float, default=2.0, help="recording past the window while the fit runs, s (2)")
    ap.add_argument("--repeat", type=int, default=3, help="recordings per rate (median reported; 3)")
    ap.add_argument("--sim", choices=("process", "in-process"), default="process",
                    help="simulated devices in their own process (default) or in the recorder's")
    ap.add_argument("--clock", default="realtime", help="in-process simulator's clock: realtime (default) or fast")
    ap.add_argument("--fit", choices=("process", "recorder", "both"), default="both",
                    help="where the online fit runs: its own process (the default setting), the recorder's "
                         "process, or both in turn (default: both, the recorder's as the second baseline)")
    args = ap.parse_args(argv)
    if args.sim == "process" and args.clock != "realtime":
        ap.error("--clock applies to --sim in-process only")
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
          f"numpy {np.__version__}; load average {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    print(f"simulated devices: {args.sim}, clock {args.clock}; window {args.window:g} s, recording "
          f"{args.after:g} s past it")
    ok = True
    modes = {"process": [True], "recorder": [False], "both": [True, False]}[args.fit]
    print(f"{'rate':>8}  {'fit in':<9}{'latency (s)':>12}{'offline fit (s)':>17}{'ratio':>7}  best  online == offline")
    with (simulator_process() if args.sim == "process" else contextlib.nullcontext()) as bench:
        for rate in (1000.0, 10000.0):
            runs = {m: ([], [], set(), [True]) for m in modes}
            for _ in range(max(1, args.repeat)):
                for mode in modes:  # interleaved: both modes see the same machine load
                    lat, off, names, same_all = runs[mode]
                    with tempfile.TemporaryDirectory() as d:
                        la, of, same, best = one(d, rate, args.window, args.after, bench, args.clock, mode)
                    lat.append(la)
                    off.append(of)
                    names.add(best)
                    same_all[0] &= same
            for mode in modes:
                lat, off, names, same_all = runs[mode]
                la, of = statistics.median(lat), statistics.median(off)
                # per run: latency / offline fit of that run (the fit's own time varies from one
                # recording to the next, so only the per-run ratio says what the recorder adds)
                ratio = statistics.median(a / b for a, b in zip(lat, off))
                print(f"{rate:>8.0f}  {'process' if mode else 'recorder':<9}{la:>12.2f}{of:>17.2f}{ratio:>7.2f}  "
                      f"{','.join(sorted(names)):<5} {'yes' if same_all[0] else 'NO'}   (latency / offline per run: "
                      f"{', '.join(f'{a:.2f}/{b:.2f}' for a, b in zip(lat, off))} s; max {max(lat):.2f} s)")
                ok &= same_all[0]
    print("issue 13: latency < 2 s at 1 and 10 kHz; the online fit identical to velab fit of the file")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
