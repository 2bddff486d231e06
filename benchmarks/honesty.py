"""Is the fit honest on a valve its rig file does not describe? (issue 51, item 6)

Records the fitter did not make: the time-domain model (MOC) with quadratic friction and the paper's
imposed sigmoid as the flow (``velab synth --material A --valve imposed``), sigma 0.1 m, 1 s pretrigger,
at 1 kHz; fitted by default head-only (no valve position: the closure is fitted) with the reference rig
file, whose valve is a butterfly on the orifice law -- not the record's. For each noise seed: the best
model, its wave speed a, the standard error, z = (a - 353.73) / SE, and S3's; then how many seeds have
the truth within 2 SE. ``--elastic``: the same on an elastic pipe (80 m, 420 m/s, no creep), where EL
should be named.

    python benchmarks/honesty.py [--seeds 1-12] [--window 20] [--elastic] [--rig-valve orifice|imposed]

``--rig-valve imposed`` fits with the record's own rig file (its valve law imposed): the closure family then
holds the record's flow exactly, the reference for what the fitted closure costs.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

from velab.config import Material, load_material, load_rig
from velab.fitting.entry import fit_record
from velab.synth import SynthSettings, synthesise, with_valve_law


def seeds(spec: str) -> list[int]:
    out = []
    for part in spec.split(","):
        lo, _, hi = part.partition("-")
        out += list(range(int(lo), int(hi or lo) + 1))
    return out


def case(elastic: bool):
    rig = load_rig("perugia")
    if elastic:
        rig = rig.with_changes(pipe=replace(rig.pipe, length_m=80.0), nominal_wave_speed_m_s=420.0)
        return rig, Material(wave_speed_m_s=420.0, elements=(), name="elastic"), 420.0, "EL"
    return rig, load_material("A"), 353.73, "S3"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1-12")
    ap.add_argument("--window", type=float, default=20.0)
    ap.add_argument("--elastic", action="store_true")
    ap.add_argument("--rig-valve", choices=("orifice", "imposed"), default="orifice")
    args = ap.parse_args()
    rig, material, a_true, truth = case(args.elastic)
    record_rig = with_valve_law(rig, "imposed")
    fit_rig = rig if args.rig_valve == "orifice" else record_rig
    inside = named = 0
    ss = seeds(args.seeds)
    for seed in ss:
        t, head, _, _ = synthesise(record_rig, material, SynthSettings(seed=seed, duration_s=args.window))
        c0 = time.process_time()
        r = fit_record(t, head, 0.0, fit_rig, args.window, record_rate_hz=1000.0)
        cpu = time.process_time() - c0
        b = r.best
        z = (b.wave_speed_m_s - a_true) / b.wave_speed_se_m_s
        inside += abs(z) <= 2
        named += b.name == truth
        t_fit = r.get(truth)
        zt = (t_fit.wave_speed_m_s - a_true) / t_fit.wave_speed_se_m_s if t_fit else float("nan")
        kappa = r.settings["manoeuvre"]["params"].get("coupling")
        nxt = sorted((f for f in r.models if f is not b), key=lambda f: f.delta_aic)[0]
        print(f"seed {seed:3d}: best {b.name} a = {b.wave_speed_m_s:.3f} +- {b.wave_speed_se_m_s:.4f} m/s, z {z:+.2f}"
              f" ({truth}: z {zt:+.2f}); next {nxt.name} dAIC {nxt.delta_aic:.1f}; F/noise {b.noise_ratio:.3f};"
              f" closure coupling {kappa:g}; {cpu:.1f} s CPU", flush=True)
    print(f"truth within 2 SE in {inside} of {len(ss)} seeds; {truth} named in {named} of {len(ss)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
