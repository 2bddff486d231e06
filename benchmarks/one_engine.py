"""One engine (issue 51): a single record fitted as a stack of one part, against the single sweep.

Each record is fitted both ways in this run -- the single sweep (velab.fitting.prepare.fit_prepared: ``_Sweep``,
one step, closure rounds, the rival's own closure, time-domain polish; the single path's engine until the
twenty-fifth round, which had added a lead fit) and a one-part stack (velab.fitting.entry.fit_record, the
product's path: velab.fitting.recordfit, velab.fitting.joint's StackedSweep) -- and
per record prints the model named, its wave speed a, the standard error, z = (a - truth) / SE, and the CPU
seconds of each; then per case how many have the truth within 2 SE, how many name the true model, and the CPU
ratio stacked / single (summed over the case's records: the baseline is this run's single sweep).

Records (as benchmarks/honesty.py and tests/fitting/test_fit_honesty.py make them): MOC records with the paper's
imposed sigmoid, fitted head-only with the reference rig file (orifice valve: the closure is fitted) --
``imposed`` material A (S3, a = 353.73 m/s), seeds 1-6; ``elastic`` (80 m, 420 m/s, no creep: EL), seeds 1-3,
models EL..S2 as the test fits them, and ``elastic-all`` the same with every model; ``default``: `velab synth`'s
record (material A on the reference rig, orifice valve, the paper's seed), its valve position recorded.
``--truths``: tests/fitting/test_fit_truths.py's records (MOC, EL..S4 on both rigs, the rig's sigmoid), fitted
as that test does (velab.fitting.fit_sweep on the window) and as a one-part stack under the rig's flow
(``manoeuvre="rig"``: what fit_sweep drives with), F compared.

    python benchmarks/one_engine.py [--cases imposed,elastic,elastic-all,default] [--seeds 1-6] [--truths]
"""

from __future__ import annotations

import argparse
import time


from velab.config import load_material, load_rig
from velab.fitting import fit_sweep
from velab.fitting.entry import fit_record
from velab.fitting.options import FitOptions
from velab.fitting.prepare import fit_prepared, prepare_record
from velab.fitting.sections import fit_sections
from velab.synth import SynthSettings, synthesise, with_valve_law

from honesty import case as honesty_case, seeds  # (the sibling script: run from benchmarks/ or as a path)

A_TRUE = 353.73
CASES = ("imposed", "elastic", "elastic-all", "default")


def records(case: str, ss: list[int]):
    """(label, t, head, position, fit rig, models, truth model, true a) of a case."""
    rig = load_rig("perugia")
    if case == "default":
        t, head, _, pos = synthesise(rig, load_material("A"), SynthSettings())
        yield "default", t, head, pos, rig, None, "S3", A_TRUE
        return
    rig, material, a_true, truth = honesty_case(case != "imposed")  # benchmarks/honesty.py's records
    models = [0, 1, 2] if case == "elastic" else None
    for seed in (ss if case == "imposed" else [s for s in ss if s <= 3]):
        t, head, _, _ = synthesise(with_valve_law(rig, "imposed"), material, SynthSettings(seed=seed, duration_s=20.0))
        yield f"seed {seed}", t, head, None, rig, models, truth, a_true


def timed(fn):
    c0 = time.process_time()
    r = fn()
    return r, time.process_time() - c0


def row(r, a_true: float, cpu: float) -> dict:
    b = r.best
    z = (b.wave_speed_m_s - a_true) / b.wave_speed_se_m_s
    return {"name": b.name, "a": b.wave_speed_m_s, "se": b.wave_speed_se_m_s, "z": z, "cpu": cpu,
            "dAIC2": sorted(f.delta_aic for f in r.models)[1] if len(r.models) > 1 else float("nan"),
            "error": b.support == "model error"}


def cell(d: dict) -> str:
    return (f"{d['name']:>3} a {d['a']:8.3f} +- {d['se']:.4f} z {d['z']:+6.2f} next {d['dAIC2']:5.1f}"
            f"{' (model error)' if d['error'] else ''} {d['cpu']:6.1f} s")


def run_case(case: str, ss: list[int]) -> dict:
    print(f"\n== {case} (single sweep | one-part stack: the fit path)", flush=True)
    tot = {"n": 0, "in1": 0, "in2": 0, "named1": 0, "named2": 0, "same": 0, "cpu1": 0.0, "cpu2": 0.0}
    for label, t, head, pos, rig, models, truth, a_true in records(case, ss):
        extra = {} if models is None else {"models": models}
        one, c1 = timed(lambda: fit_prepared(prepare_record(t, head, 0.0, rig, 20.0, record_rate_hz=1000.0,
                                                           position_pct=pos), rig, FitOptions.of(**extra)))
        two, c2 = timed(lambda: fit_record(t, head, 0.0, rig, 20.0, record_rate_hz=1000.0, position_pct=pos, **extra))
        d1, d2 = row(one, a_true, c1), row(two, a_true, c2)
        rounds = [n for n in two.notes if "refined again" in n or "under the closure refined with its own" in n]
        print(f"{label:>8}: {cell(d1)} | {cell(d2)}" + (f"  [stack: {'; '.join(rounds)}]" if rounds else ""),
              flush=True)
        tot["n"] += 1
        tot["in1"] += abs(d1["z"]) <= 2
        tot["in2"] += abs(d2["z"]) <= 2
        tot["named1"] += d1["name"] == truth
        tot["named2"] += d2["name"] == truth
        tot["same"] += d1["name"] == d2["name"]
        tot["cpu1"] += c1
        tot["cpu2"] += c2
    tot["truth"] = truth
    return tot


def truths() -> None:
    """tests/fitting/test_fit_truths.py's records through fit_sweep (the test's path) and a one-part stack."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "fitting"))
    from test_fit_truths import TRUTHS, _record

    print("\n== truths (fit_sweep as the test | one-part stack, manoeuvre rig)", flush=True)
    same = named = n = 0
    cpu1 = cpu2 = 0.0
    for rig_name in ("perugia", "imperial"):
        rig = load_rig(rig_name)
        for truth in TRUTHS:
            t, h = _record(rig, truth)
            one, c1 = timed(lambda: fit_sweep(t, h, rig))
            two, c2 = timed(lambda: fit_sections(t, {rig.head_section.name: rig.steady_head_m + h}, 0.0, rig, None,
                                                 record_rate_hz=1000.0, manoeuvre="rig"))
            a = rig.nominal_wave_speed_m_s
            d1, d2 = row(one, a, c1), row(two, a, c2)
            dF = two.best.F / one[two.best.name].F - 1
            print(f"{rig_name:>8} {truth}: {cell(d1)} | {cell(d2)}  F(stack)/F(single) - 1 = {dF:+.1e}", flush=True)
            n += 1
            same += d1["name"] == d2["name"]
            named += d2["name"] == truth
            cpu1 += c1
            cpu2 += c2
    print(f"truths: same model named {same}/{n}; stack names the truth {named}/{n}; CPU stacked/single "
          f"{cpu2 / cpu1:.2f}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--seeds", default="1-6")
    ap.add_argument("--truths", action="store_true")
    args = ap.parse_args()
    ss = seeds(args.seeds)
    sums = {c: run_case(c, ss) for c in args.cases.split(",") if c}
    print("\ncase         records  truth in 2 SE (single, stack)  true model named (single, stack)  same model  "
          "CPU stack/single")
    for c, s in sums.items():
        print(f"{c:<12} {s['n']:>7}  {s['in1']}/{s['n']}, {s['in2']}/{s['n']:<22} {s['truth']}: {s['named1']}/{s['n']}, "
              f"{s['named2']}/{s['n']:<22} {s['same']}/{s['n']:<9} {s['cpu2'] / s['cpu1']:.2f}")
    if args.truths:
        truths()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
