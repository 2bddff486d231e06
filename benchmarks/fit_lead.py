"""The fit path's two steps against one (velab.fitting.lead): what the lead fit costs offline, and
what is left for the recorder once the window has closed (the continuation).

Material A on the reference rig, 20 s at 1 kHz with 1 s before the trigger: with linear friction
(the frequency model's own, sigma 0.1 m) and with quadratic friction (the time-domain MOC head, sigma
0.012 m, as the simulator records it). Each case is fitted by ``fit_record`` with ``lead=False`` (one
step: the baseline, in the same run) and by default (lead + continuation), in turn, ``--repeat``
times; medians. Prints the fit path's time and its ratio to one step, the continuation's own time
(the online latency's share of the fit) and its ratio to one step, and whether both name the same
model with F no more than 1e-4 apart.

    python benchmarks/fit_lead.py              # both cases, 3 repeats
    python benchmarks/fit_lead.py --repeat 1
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time

import numpy as np

from velab.config import load_material, load_rig
from velab.fitting import fit_record
from velab.model import creep_scale, valve_head
from velab.moc import moc_head


def records():
    mat = load_material("A")
    fs = 1000.0
    t = np.arange(-int(fs), int(20 * fs)) / fs
    lin = load_rig("perugia").with_changes(friction="linear")
    h_lin = lin.steady_head_m + valve_head(t, lin, mat) + np.random.default_rng(2018).normal(0, 0.1, t.size)
    quad = load_rig("perugia")
    a = quad.nominal_wave_speed_m_s
    J = np.array([creep_scale(quad, a) / e.E_pa for e in mat.elements])  # J'_k = c a^2 / E_k
    tau = np.array([e.tau_s for e in mat.elements])
    h_quad = quad.steady_head_m + moc_head(quad, a, J, tau, t) + np.random.default_rng(2019).normal(0, 0.012, t.size)
    return {"material A, linear, sigma 0.1": (t, h_lin, lin, fs),
            "material A, quadratic (MOC), sigma 0.012": (t, h_quad, quad, fs)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
          f"numpy {np.__version__}; load average {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    ok = True
    print(f"{'record':<44}{'one step (s)':>13}{'fit path (s)':>13}{'x one':>7}{'continuation (s)':>17}{'x one':>7}"
          "  same model, F within 1e-4")
    for name, (t, h, rig, fs) in records().items():
        kw = dict(t_s=t, head_m=h, trigger_time_s=0.0, rig=rig, window_s=20.0, record_rate_hz=fs)
        fit_record(lead=False, **kw)  # warm-up (kernels, caches)
        one, two, cont = [], [], []
        for _ in range(max(1, args.repeat)):
            t0 = time.perf_counter()
            a = fit_record(lead=False, **kw)
            one.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            b = fit_record(**kw)
            two.append(time.perf_counter() - t0)
            cont.append(b.duration_s - b.settings["lead"]["duration_s"])  # (duration_s holds both steps)
        o, w, c = statistics.median(one), statistics.median(two), statistics.median(cont)
        same = a.best.name == b.best.name and all(abs(y.F / x.F - 1) <= 1e-4 for x, y in zip(a.models, b.models))
        worst = max(abs(y.F / x.F - 1) for x, y in zip(a.models, b.models))
        ok &= same
        print(f"{name:<44}{o:>13.2f}{w:>13.2f}{w / o:>7.2f}{c:>17.2f}{c / o:>7.2f}  {'yes' if same else 'NO'} "
              f"({a.best.name} / {b.best.name}; max |dF/F| {worst:.1e})")
    print("the continuation is what is left when the recorder's window closes (issue 13: latency < 2 s)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
