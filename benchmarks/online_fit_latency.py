"""Online-fit latency: from the fit window closing to the final fit, at 1 kHz and 10 kHz (issue 13:
< 2 s), against the same fit run offline on the recorded file in the same run (the baseline).

Each case records material A with the simulated rig (``velab record --simulate``'s recorder, the
fast clock: 12 x real time), duration equal to the fit window (20 s by default), models EL..S6,
then re-fits the run file with ``velab.fitting.fit_run`` (what ``velab fit`` does) and checks
that the result is the online one. Latency = the recorder's ``fit_latency_s``; the ratio
latency / offline fit time says how much of the latency is the fit itself (1.0: all of it).

    python benchmarks/online_fit_latency.py                 # 1 and 10 kHz, 20 s window
    python benchmarks/online_fit_latency.py --window 10 --repeat 2
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import tempfile
import time

import numpy as np

from velab.fitting import SweepResult, fit_run
from velab.recording import Recorder, RecordSettings
from velab.runfile import read_run
from velab.runfiles.summary import read_fits


def one(folder: str, rate: float, window_s: float) -> tuple[float, float, bool, str]:
    s = RecordSettings(duration_s=window_s, fit_window_s=window_s, pretrigger_s=1.5, sample_rate_hz=rate,
                       out_dir=folder)
    with Recorder.simulated(s, "default", material="A", clock="fast") as rec:
        summary = rec.run()
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
    ap.add_argument("--window", type=float, default=20.0, help="fit window = duration, s (20)")
    ap.add_argument("--repeat", type=int, default=1, help="recordings per rate (median reported)")
    args = ap.parse_args(argv)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
          f"numpy {np.__version__}; load average {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    ok = True
    print(f"{'rate':>8}{'latency (s)':>13}{'offline fit (s)':>17}{'ratio':>7}  best  online == offline")
    for rate in (1000.0, 10000.0):
        lat, off, names, same_all = [], [], set(), True
        for _ in range(max(1, args.repeat)):
            with tempfile.TemporaryDirectory() as d:
                la, of, same, best = one(d, rate, args.window)
            lat.append(la)
            off.append(of)
            names.add(best)
            same_all &= same
        la, of = statistics.median(lat), statistics.median(off)
        print(f"{rate:>8.0f}{la:>13.2f}{of:>17.2f}{la / of:>7.2f}  {','.join(sorted(names)):<5} "
              f"{'yes' if same_all else 'NO'}   (latencies {', '.join(f'{v:.2f}' for v in lat)} s)")
        ok &= same_all
    print("issue 13: latency < 2 s at 1 and 10 kHz; the online fit identical to velab fit of the file")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
