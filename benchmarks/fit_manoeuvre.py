"""The cost of the manoeuvre in the fit (issue 24): the default fit path with the flow at the valve
built from the record (a closure fitted with the wall, velab.fitting.manoeuvre) and the models ending
on the time-domain model's own optimum, against the fit path as it was (the rig's sigmoid imposed as
the flow, no time-domain polish), side by side on the same records, in the same run.

Records (material A on the reference rig, quadratic friction, sigma 0.1 m, 1 s pretrigger, 20 s at
1 kHz, made by the time-domain model):
* "real valve": the butterfly on the orifice law, the actuator on the rig's sigmoid in position;
* "imposed": the rig's sigmoid imposed as the flow (the paper's valve model): the previous fit path
  names the truth there too, so the two do the same work and the ratio is the manoeuvre's price.

The paths run in turn within each repeat (the drift of a virtual machine's speed shared alike), and the
CPU ratio of each repeat is printed as well.

    python benchmarks/fit_manoeuvre.py [--repeat 3]

Prints, per record and fit path: the median time (and each repeat), the best model, its wave speed,
its F / noise; then the ratios new / previous, of the wall time and of the CPU time (the process's,
both threads: steadier than the wall time on a loaded machine). The target (issue 24): the new
default (fitted manoeuvre and time-domain polish) costs at most 1.3 x the previous default fit of the
same record; on the "imposed" record, where both find the truth, the two do the same work. On the
"real valve" one the previous path ends fast on a wrong model (F 70x the noise): its ratio is
printed, not a target. Timings depend on the load: check `uptime` first.
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import time

import numpy as np

from velab.config import load_material, load_rig
from velab.fitting import sweep as fit_sweep_module
from velab.fitting.entry import fit_record
from velab.model import creep_scale
from velab.moc import moc_head
from velab.valvelaw import commanded_position_pct


def record(valve: str, seed: int = 2018):
    rig = load_rig("perugia")
    mat = load_material("A")
    a = mat.wave_speed_m_s
    J = np.array([e.J_per_pa for e in mat.elements]) * creep_scale(rig, a)
    tau = np.array([e.tau_s for e in mat.elements])
    t = np.arange(-1000, 20000) / 1000.0
    m = rig.manoeuvre
    kw = {"position": lambda x: commanded_position_pct(x, m.beta_per_s, m.gamma)} if valve == "real valve" else {}
    h = moc_head(rig, a, J, tau, t, **kw)
    return rig, t, rig.steady_head_m + h + np.random.default_rng(seed).normal(0.0, 0.1, t.size)


@contextlib.contextmanager
def polish(on: bool):
    old = fit_sweep_module.MOC_POLISH
    fit_sweep_module.MOC_POLISH = on
    try:
        yield
    finally:
        fit_sweep_module.MOC_POLISH = old


PATHS = {
    "previous (rig sigmoid)": dict(manoeuvre="rig", polish=False),
    "closure only": dict(manoeuvre="auto", polish=False),
    "new default": dict(manoeuvre="auto", polish=True),
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    for valve in ("imposed", "real valve"):
        rig, t, h = record(valve)
        fit_record(t, h, 0.0, rig, 20.0, record_rate_hz=1000.0, models=[0], manoeuvre="rig")  # warm-up
        medians = {}
        print(f"\n{valve} record")
        # the paths in turn, repeat after repeat (not each path's repeats in a row): a virtual machine's speed
        # drifts by 10-20 % within minutes, and interleaving gives every path the same share of the drift
        times = {name: [] for name in PATHS}
        cpus = {name: [] for name in PATHS}
        results = {}
        for _ in range(args.repeat):
            for name, opts in PATHS.items():
                with polish(opts["polish"]):
                    t0, c0 = time.perf_counter(), time.process_time()
                    results[name] = fit_record(t, h, 0.0, rig, 20.0, record_rate_hz=1000.0,
                                               manoeuvre=opts["manoeuvre"])
                    times[name].append(time.perf_counter() - t0)
                    cpus[name].append(time.process_time() - c0)
        for name in PATHS:
            medians[name] = statistics.median(times[name]), statistics.median(cpus[name])
            b = results[name].best
            print(f"  {name:24s} {medians[name][0]:6.2f} s wall, {medians[name][1]:6.2f} s CPU  "
                  f"({', '.join(f'{x:.2f}' for x in times[name])})  best {b.name}, "
                  f"a = {b.wave_speed_m_s:.3f} m/s, F/noise {b.noise_ratio:.3f}")
        base = medians["previous (rig sigmoid)"]
        for i, what in enumerate(("wall", "CPU")):
            print(f"  ratio ({what}) closure only / previous: {medians['closure only'][i] / base[i]:.2f}; "
                  f"new default / previous: {medians['new default'][i] / base[i]:.2f} (target <= 1.3)")
        paired = [c / b for c, b in zip(cpus["new default"], cpus["previous (rig sigmoid)"])]
        print(f"  paired CPU ratios new default / previous, repeat by repeat: {', '.join(f'{x:.2f}' for x in paired)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
