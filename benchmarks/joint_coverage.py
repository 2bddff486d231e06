"""Does the joint fit's 95 % creep band hold? (issue 51: "a reported uncertainty must hold")

The recipe of the joint fit's acceptance test (tests/fitting/test_fit_joint.py): ``velab synth`` on the reference
rig -- the real butterfly valve on its sigmoid in position, the orifice law, quadratic friction -- material A,
sigma 0.1 m, 0.6 s pretrigger, three runs at 2.5, 3.64 and 4.5 l/s, exported as head-only CSVs and brought back
by ``velab import`` (every run's closure fitted), then ``fit_joint``. A campaign ``B`` uses the noise seeds B,
B + 1, B + 2 (the test's campaigns are 21 and 41). For each campaign: the best model, and
z = (estimate - truth) / reported SE of ln(J(t) - J0) at t = 0.05, 0.5 and 5 s (the band's half-width / 1.96)
and of the wave speed, for the best model, for S3 (the truth's) and for the model-averaged creep; then the mean,
the standard deviation and the counts beyond 1.96 and 2.58 over the campaigns. A band that holds gives means
near 0, standard deviations near 1 and about 5 % and 1 % of the points beyond.

    python benchmarks/joint_coverage.py [--campaigns 501-1701:20] [--window 8] [--position] [--free-shape]

``--position``: the synth files themselves (head and valve position: no closure fitted). ``--free-shape``: every
run's closure shape fitted (``closurefit.SHAPE_PRICE`` set to -inf: what a run whose first part frees its shape
does). About 10 s of CPU per campaign at 8 s windows (docs/fitting.md, "Joint fits": the measured tables).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import tempfile
import time
from pathlib import Path

import numpy as np

from velab.cli import main as velab
from velab.config import load_material
from velab.fitting.campaignrun import CampaignRun
from velab.fitting.creep import Z95, creep_curve
from velab.fitting.joint import fit_joint
from velab.fitting.selection import averaged_creep_of
from velab.runfiles import read_run

RIG = Path(__file__).resolve().parents[1] / "configs" / "rigs" / "perugia.toml"
FLOWS_L_S = (2.5, 3.64, 4.5)
TIMES_S = np.array([0.05, 0.5, 5.0])
A_TRUE = 353.73


def campaigns(spec: str) -> list[int]:
    """``lo-hi:step`` or a comma-separated list."""
    if "-" in spec:
        rng, _, step = spec.partition(":")
        lo, hi = map(int, rng.split("-"))
        return list(range(lo, hi + 1, int(step or 1)))
    return [int(s) for s in spec.split(",")]


def runs_of(tmp: Path, base: int, window_s: float, position: bool) -> list[CampaignRun]:
    out = []
    for i, q in enumerate(FLOWS_L_S):
        rig = tmp / f"rig_{base}_{i}.toml"
        rig.write_text(RIG.read_text().replace("steady_flow_m3_s = 3.64e-3", f"steady_flow_m3_s = {q / 1e3!r}"))
        synth, csv, run = (tmp / f"{k}_{base}_{i}{e}" for k, e in (("synth", ".h5"), ("head", ".csv"), ("run", ".h5")))
        with contextlib.redirect_stdout(io.StringIO()):
            assert velab(["synth", "--rig", str(rig), "--material", "A", "--duration", str(window_s), "--pretrigger",
                          "0.6", "--seed", str(base + i), "-o", str(synth), "-q"]) == 0
            if not position:
                rec = read_run(synth)
                with open(csv, "w") as f:
                    f.write("time_s,head_m\n")
                    for a, b in zip(rec.time_s, rec.head_m):
                        f.write(f"{a:.6f},{b:.6f}\n")
                assert velab(["import", str(csv), "--rig", str(rig), "-o", str(run), "-q"]) == 0
        out.append(CampaignRun.from_run(read_run(synth if position else run)))
    return out


def z_creep(curve, truth) -> np.ndarray:
    sd = np.log(curve.upper / curve.lower) / (2 * Z95)
    return np.log(curve.J_per_pa / truth) / sd


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--campaigns", default="501-1701:20")
    ap.add_argument("--window", type=float, default=8.0)
    ap.add_argument("--position", action="store_true")
    ap.add_argument("--free-shape", action="store_true")
    args = ap.parse_args(argv)
    if args.free_shape:
        import velab.fitting.closurefit as closurefit

        closurefit.SHAPE_PRICE = -np.inf
    truth = load_material("A").creep_compliance(TIMES_S)
    rows = {"best": [], "S3": [], "averaged": []}
    for base in campaigns(args.campaigns):
        with tempfile.TemporaryDirectory() as tmp:
            runs = runs_of(Path(tmp), base, args.window, args.position)
        c0 = time.process_time()
        r = fit_joint(runs, args.window)
        cpu = time.process_time() - c0
        line = []
        for key, fit in (("best", r.best), ("S3", r.get("S3"))):
            z = z_creep(creep_curve(fit, t_s=TIMES_S), truth)
            za = (fit.wave_speed_m_s - A_TRUE) / fit.wave_speed_se_m_s
            rows[key].append([*z, za])
            line.append(f"{key} {fit.name if key == 'best' else ''} z {' '.join(f'{v:+.2f}' for v in z)} a {za:+.2f}")
        avg = averaged_creep_of(r, t_s=TIMES_S)
        za = z_creep(avg.curve, truth)
        rows["averaged"].append(list(za))
        print(f"campaign {base}: {'; '.join(line)}; averaged z {' '.join(f'{v:+.2f}' for v in za)} (S3 weight "
              f"{avg.weights.get('S3', 0.0):.2f}); shapes {[x['manoeuvre'].get('shape') for x in r.runs]}; "
              f"{cpu:.1f} s CPU", flush=True)
    n = len(rows["best"])
    print(f"\n{n} campaigns; z at 0.05, 0.5, 5 s and of the wave speed")
    for key, v in rows.items():
        Z = np.array(v)
        fmt = lambda a: " ".join(f"{x:+5.2f}" for x in a)  # noqa: E731
        cnt = lambda k: " ".join(f"{int(x):2d}" for x in (np.abs(Z) > k).sum(axis=0))  # noqa: E731
        print(f"{key:9s} mean {fmt(Z.mean(0))}  sd {fmt(Z.std(0, ddof=1) if n > 1 else Z[0] * np.nan)}  "
              f"beyond 1.96: {cnt(1.96)}  beyond 2.58: {cnt(2.58)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
