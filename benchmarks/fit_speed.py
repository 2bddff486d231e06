"""The default fit's own speed (issue 51, What to build 7: ``velab fit`` of the default synthetic record, 20 s
at 1 kHz, within 1 s wall on two cores): the fit path of today (the record as a stack of one part,
velab.fitting.recordfit) against the single sweep (velab.fitting.prepare.fit_prepared: ``_Sweep``, one step, the
engine of the single path until this round, whose path then added a lead fit), in the same process, in turn; and
``velab fit FILE --no-save`` as a user runs it (a fresh process: imports and the time-domain kernel's cache load
included).

The record is ``velab synth --material A`` (made once in a temporary folder). Both paths must give the same best
model and every model's wave speed to a small fraction of its standard error (printed).

    python benchmarks/fit_speed.py [--repeat 3] [--no-cli]

Prints the medians (wall and CPU: the process's, both threads) and each repeat, their ratio new / baseline,
and the CLI's wall and CPU time. Timings depend on the load: check ``uptime`` first (printed).
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time

from velab.fitting import fit_run
from velab.fitting.prepare import fit_prepared, prepare_record
from velab.moc import warm_up
from velab.runfiles import read_run


def single_sweep(run):
    """The baseline: the record prepared as fit_run does and fitted by the single sweep (one step)."""
    rec = prepare_record(run.time_s, run.head_m, run.trigger_time_s, run.rig, None, record_rate_hz=run.sample_rate_hz,
                         position_pct=run.channels.get("valve_position"))
    return fit_prepared(rec, run.rig)


def cli_fit(path: str) -> tuple[float, float]:
    """(wall, CPU) of ``velab fit path --no-save`` in a fresh process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "velab.cli", "fit", path, "--no-save"], check=True,
                   stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-cli", action="store_true", help="skip the fresh-process `velab fit` timing")
    args = ap.parse_args(argv)
    print(f"{os.cpu_count()} cores; load average {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "a.h5")
        subprocess.run([sys.executable, "-m", "velab.cli", "synth", "--material", "A", "-o", path], check=True,
                       stdout=subprocess.DEVNULL)
        run = read_run(path)
        warm_up()
        fit_run(run, None, models=[0])  # warm-up (first calls: caches, buffers)
        times = {False: [], True: []}
        results = {}
        for _ in range(args.repeat):
            for on in (False, True):  # in turn: both see the same drift of the machine's speed
                t0, c0 = time.perf_counter(), time.process_time()
                results[on] = fit_run(run, None) if on else single_sweep(run)
                times[on].append((time.perf_counter() - t0, time.process_time() - c0))
        med = {on: (statistics.median(w for w, _ in v), statistics.median(c for _, c in v)) for on, v in times.items()}
        for on, label in ((False, "single sweep (baseline)"), (True, "the stack (fit path)")):
            b = results[on].best
            print(f"  {label:24s} {med[on][0]:6.2f} s wall {med[on][1]:6.2f} s CPU  "
                  f"({', '.join(f'{w:.2f}/{c:.2f}' for w, c in times[on])})  best {b.name}, "
                  f"a = {b.wave_speed_m_s:.4f} m/s")
        print(f"  ratio stack / single sweep: wall {med[True][0] / med[False][0]:.2f}, "
              f"CPU {med[True][1] / med[False][1]:.2f}")
        worst = 0.0
        for old, new in zip(results[False].models, results[True].models):
            se = old.wave_speed_se_m_s if old.wave_speed_se_m_s and old.wave_speed_se_m_s > 0 else float("nan")
            worst = max(worst, abs(new.wave_speed_m_s - old.wave_speed_m_s) / se)
        same = results[False].best.name == results[True].best.name
        print(f"  same best model: {'yes' if same else 'NO'}; largest wave-speed change {worst:.2g} SE")
        if not args.no_cli:
            cli = [cli_fit(path) for _ in range(args.repeat)]
            print(f"  velab fit --no-save (fresh process): {statistics.median(w for w, _ in cli):.2f} s wall, "
                  f"{statistics.median(c for _, c in cli):.2f} s CPU ({', '.join(f'{w:.2f}/{c:.2f}' for w, c in cli)}); "
                  f"target <= 1 s wall on two cores")
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
