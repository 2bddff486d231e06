"""`velab fit` over an archive: local --jobs 1 (the baseline) against --jobs 2 and a Dask cluster.

    python benchmarks/batch_fit.py                       # 24 runs, 6 s at 1 kHz, EL..S3
    python benchmarks/batch_fit.py --runs 50 --models 0-6 --duration 20
    python benchmarks/batch_fit.py --scheduler tcp://10.0.0.5:8786   # a real cluster instead of a LocalCluster

Each configuration fits the same archive (copies of a few synthetic runs of materials A and B)
through velab.batch.runner.run_batch, the code behind `velab fit RUN... [--jobs N | --scheduler
ADDRESS]`, saving every fit into its run (the client writes, one file at a time). The figures
are wall times of whole batches; the ratios are to `--jobs 1` (this process, one run after
another) measured in the same run, which is what to compare across machines and loads. The
LocalCluster (2 worker processes, 1 thread each, loopback) is started before its batch is
timed; its start-up is printed on its own. Needs the velab[cluster] extra for the cluster line.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path


def make_archive(d: Path, runs: int, duration: float, rate: float) -> tuple[list[str], list[Path]]:
    from velab.cli import main as velab

    sources = []
    for material, seed in (("A", 1), ("B", 2), ("A", 3), ("B", 4)):
        p = d / f"src_{material}{seed}.h5"
        assert velab(["-q", "synth", "--material", material, "--seed", str(seed), "--duration", str(duration),
                      "--rate", str(rate), "-o", str(p)]) == 0
        sources.append(p)
    return [str(d / f"run{i:03d}.h5") for i in range(runs)], sources


def fresh(paths: list[str], sources: list[Path]) -> None:
    for i, p in enumerate(paths):
        shutil.copy(sources[i % len(sources)], p)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=24)
    ap.add_argument("--duration", type=float, default=6.0, help="record after the trigger, s")
    ap.add_argument("--rate", type=float, default=1000.0)
    ap.add_argument("--models", default="0-3")
    ap.add_argument("--window", type=float, default=5.0)
    ap.add_argument("--scheduler", default=None, help="a running scheduler instead of a LocalCluster")
    ap.add_argument("--no-cluster", action="store_true")
    args = ap.parse_args()

    from velab.batch.runner import run_batch
    from velab.commands.fit import fit_file, fit_request
    from velab.fitting.sweep import parse_models

    opts = {"models": parse_models(args.models), "window_s": args.window, "method": "auto", "reduced": False,
            "starts": None, "polish": True, "save": True, "name": None, "plot": None, "tau_min_s": None,
            "tau_max_s": None, "selection": "ar1", "friction": None, "friction_unsteady": None}
    print(f"{args.runs} runs of {args.duration:g} s at {args.rate:g} Hz, models {args.models}, window "
          f"{args.window:g} s; {os.cpu_count()} cores")
    with tempfile.TemporaryDirectory(dir=".") as d:
        paths, sources = make_archive(Path(d), args.runs, args.duration, args.rate)
        fit_file(str(sources[0]), {**opts, "save": False})  # imports and caches warm, out of the timings

        def timed(label, **kw):
            fresh(paths, sources)
            t0 = time.perf_counter()
            batch = run_batch(fit_request, paths, opts, **kw)
            seconds = time.perf_counter() - t0
            failed = [o for o in batch.outcomes if not o["ok"]]
            assert not failed, failed[0]
            fit_s = sum(o["seconds"] for o in batch.outcomes)
            best = {o["fit"]["best"] for o in batch.outcomes}
            return label, seconds, fit_s, best

        rows = [timed("local --jobs 1", jobs=1), timed("local --jobs 2", jobs=2)]
        if not args.no_cluster:
            address, cluster = args.scheduler, None
            if address is None:
                from distributed import LocalCluster

                t0 = time.perf_counter()
                cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                       scheduler_port=0, dashboard_address=None)
                address = cluster.scheduler_address
                print(f"LocalCluster (2 worker processes) started in {time.perf_counter() - t0:.1f} s")
            try:
                timed(f"dask {address} (first batch: workers import velab)", scheduler=address)
                rows.append(timed(f"dask {address}", scheduler=address))
            finally:
                if cluster is not None:
                    cluster.close()
    base = rows[0][1]
    print(f"{'configuration':<44}{'batch (s)':>10}{'runs/s':>8}{'sum of fits (s)':>17}{'x jobs 1':>10}  best")
    for label, seconds, fit_s, best in rows:
        print(f"{label:<44}{seconds:>10.2f}{args.runs / seconds:>8.2f}{fit_s:>17.2f}{base / seconds:>10.2f}  "
              f"{','.join(sorted(best))}")


if __name__ == "__main__":
    main()
