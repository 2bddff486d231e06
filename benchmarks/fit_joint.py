"""A joint fit of a campaign against one run's default fit (velab.fitting.joint; issue 25: a joint fit of
5 runs must cost at most 3 x one run's fit).

Five head-only runs of material A's pipe on the reference rig, made by the time-domain model with the
real butterfly valve on a sigmoid in position, the orifice law and quadratic friction, sigma 0.1 m: steady
flows 2.5, 3.0, 3.64, 4.0 and 4.5 l/s, actuator beta 28-36 1/s, one of them recorded at 2 kHz. Timed
in the same process, in turn, ``--repeat`` times (medians): the default fit path of the reference run
(``fit_record``: the record as a stack of one part, its closure fitted) and ``fit_joint`` of the five.
Prints both (wall and CPU time), the ratios (target <= 2.5, issue 51; 3 in issue 25) and the joint fit's best model, wave speed and
runs' noise ratios.

    python benchmarks/fit_joint.py                  # 20 s windows, 1 repeat
    python benchmarks/fit_joint.py --window 8 --repeat 3
    python benchmarks/fit_joint.py --rig imperial   # the same campaign on another rig (its Q0 x the same ratios)
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import numpy as np

from velab.config import load_material, load_rig
from velab.fitting.campaignrun import CampaignRun, head_sha256
from velab.fitting.joint import fit_joint
from velab.fitting.entry import fit_record
from velab.model import creep_scale
from velab.moc import moc_head
from velab.valvelaw import commanded_position_pct

# (Q0 l/s, actuator beta 1/s, record rate Hz)
CAMPAIGN = ((3.64, 32.0, 1000.0), (2.5, 28.0, 1000.0), (3.0, 36.0, 2000.0), (4.0, 30.0, 1000.0), (4.5, 34.0, 1000.0))


def campaign(window_s: float, rig_name: str = "perugia") -> list[CampaignRun]:
    """The five runs on ``rig_name``: on another rig than the reference one, each Q0 is the rig's own times the
    campaign's ratio to 3.64 l/s, and each actuator rate the rig's times the campaign's ratio to 32 1/s."""
    mat = load_material("A")
    base = load_rig(rig_name)
    out = []
    for i, (q0, beta, fs) in enumerate(CAMPAIGN):
        m = base.manoeuvre
        if rig_name != "perugia":
            q0, beta = base.steady_flow_m3_s * 1e3 * q0 / CAMPAIGN[0][0], m.beta_per_s * beta / CAMPAIGN[0][1]
        rig = base.with_changes(steady_flow_m3_s=q0 / 1e3,
                                manoeuvre=type(m)(beta_per_s=beta, gamma=-beta * m.half_closure_s))
        a = mat.wave_speed_m_s
        J = creep_scale(rig, a) * np.array([e.J_per_pa for e in mat.elements])
        tau = np.array([e.tau_s for e in mat.elements])
        t = np.arange(-int(fs), int(window_s * fs)) / fs
        mm = rig.manoeuvre
        h = moc_head(rig, a, J, tau, t, position=lambda x, mm=mm: commanded_position_pct(x, mm.beta_per_s, mm.gamma))
        h = rig.steady_head_m + h + np.random.default_rng(100 + i).normal(0.0, 0.1, t.size)
        out.append(CampaignRun(f"run{i + 1}_{q0:.3g}lps", t, h, 0.0, rig, fs, None, head_sha256(t, h)))
    return out


def timed(fn):
    """fn()'s result and its (wall, CPU) seconds: the process's CPU, both threads."""
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return out, (time.perf_counter() - t0, time.process_time() - c0)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--window", type=float, default=20.0)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--rig", default="perugia", help="a rig name or TOML file (default: perugia, the reference rig)")
    args = ap.parse_args(argv)
    runs = campaign(args.window, args.rig)
    ref = runs[0]
    print(f"# {platform.machine()} {os.cpu_count()} cores, python {platform.python_version()}, numpy {np.__version__};"
          f" load {os.getloadavg()[0]:.2f}; rig {args.rig}, window {args.window:g} s, {len(runs)} runs")
    single, joint = [], []  # (wall, CPU) of each repeat
    for _ in range(args.repeat):
        one, times = timed(lambda: fit_record(ref.time_s, ref.head_m, 0.0, ref.rig, args.window,
                                              record_rate_hz=ref.record_rate_hz))
        single.append(times)
        result, times = timed(lambda: fit_joint(runs, args.window))
        joint.append(times)
    s, sc = (statistics.median(c) for c in zip(*single))
    j, jc = (statistics.median(c) for c in zip(*joint))
    b = result.best
    print(f"single fit of {ref.path}: {s:.2f} s, {sc:.2f} s CPU (best {one.best.name}, "
          f"a = {one.best.wave_speed_m_s:.3f} +- {one.best.wave_speed_se_m_s:.3f} m/s)")
    print(f"joint fit of {len(runs)} runs: {j:.2f} s, {jc:.2f} s CPU (best {b.name}, a = {b.wave_speed_m_s:.3f} +- "
          f"{b.wave_speed_se_m_s:.3f} m/s; noise ratios "
          + ", ".join(f"{r['noise_ratio']:.3f}" for r in result.runs) + ")")
    print(f"ratio joint / single: {j / s:.2f} wall (target <= 2.5), {jc / sc:.2f} CPU (both threads: steadier on a "
          f"machine that is not quiet)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
