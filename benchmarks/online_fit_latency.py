"""Online-fit latency: from the fit window closing to the final fit, at 1 kHz and 10 kHz (issue 13:
< 2 s), against the same fit run offline on the recorded file in the same run (the baseline).

Each case records material A on the simulated rig (quadratic friction) in real time, models EL..S6,
the run going on for ``--after`` seconds past the fit window (the recorder keeps acquiring at the
full rate while the fit runs, as in a normal run), then re-fits the run file with
``velab.fitting.fit_run`` (what ``velab fit`` does) and checks that the result is the online one.
Latency = the recorder's ``fit_latency_s``; the ratio latency / offline fit time says how much of
the latency is the fit itself (1.0: all of it).

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
from velab.runfile import read_run
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


def one(folder: str, rate: float, window_s: float, after_s: float, bench, clock: str) -> tuple[float, float, bool, str]:
    s = RecordSettings(duration_s=window_s + after_s, fit_window_s=window_s, pretrigger_s=1.5, sample_rate_hz=rate,
                       out_dir=folder)
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
    args = ap.parse_args(argv)
    if args.sim == "process" and args.clock != "realtime":
        ap.error("--clock applies to --sim in-process only")
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
          f"numpy {np.__version__}; load average {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    print(f"simulated devices: {args.sim}, clock {args.clock}; window {args.window:g} s, recording "
          f"{args.after:g} s past it")
    ok = True
    print(f"{'rate':>8}{'latency (s)':>13}{'offline fit (s)':>17}{'ratio':>7}  best  online == offline")
    with (simulator_process() if args.sim == "process" else contextlib.nullcontext()) as bench:
        for rate in (1000.0, 10000.0):
            lat, off, names, same_all = [], [], set(), True
            for _ in range(max(1, args.repeat)):
                with tempfile.TemporaryDirectory() as d:
                    la, of, same, best = one(d, rate, args.window, args.after, bench, args.clock)
                lat.append(la)
                off.append(of)
                names.add(best)
                same_all &= same
            la, of = statistics.median(lat), statistics.median(off)
            print(f"{rate:>8.0f}{la:>13.2f}{of:>17.2f}{la / of:>7.2f}  {','.join(sorted(names)):<5} "
                  f"{'yes' if same_all else 'NO'}   (latencies {', '.join(f'{v:.2f}' for v in lat)} s; "
                  f"max {max(lat):.2f} s)")
            ok &= same_all
    print("issue 13: latency < 2 s at 1 and 10 kHz; the online fit identical to velab fit of the file")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
