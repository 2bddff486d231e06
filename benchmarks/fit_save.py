"""Saving a fit into a run: the atomic copy-and-rename save against a plain file copy.

    python benchmarks/fit_save.py                 # a 10 kHz x 10 min recording (7 fast channels, ~340 MB)
    python benchmarks/fit_save.py --minutes 1     # ~34 MB

The run is written with velab's RunWriter (the recorder's channel set); the fit is
a real stored fit (EL, S1..S3 on synthetic data). The figure is the wall time of
`velab.runfiles.save_fit`, the baseline `shutil.copyfile` of the same file measured
in the same run; the ratio (save / copy) is what to compare across machines and loads.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np


def make_run(path: Path, rate: float, seconds: float) -> None:
    from velab.config import load_rig
    from velab.runfiles import Channel, HEAD, RunWriter

    chans = (HEAD, Channel("valve_position", "%"), Channel("pressure", "Pa"), Channel("pressure_raw", "1", "i4"),
             Channel("valve_position_raw", "1", "i4"), Channel("sample_index", "1", "i8"), Channel("host_time", "s"))
    w = RunWriter(path, load_rig("perugia"), sample_rate_hz=rate, channels=chans)
    block = int(rate)
    for i in range(int(seconds)):
        t = (np.arange(block) + i * block) / rate
        w.append(t, head=30 + np.sin(t), valve_position=np.full(block, 100.0), pressure=t * 1e3,
                 pressure_raw=np.arange(block, dtype=np.int32), valve_position_raw=np.zeros(block, np.int32),
                 sample_index=np.arange(block) + i * block, host_time=t + 1.7e9)
    w.close()


def a_fit():
    from velab.fitting import fit_sweep
    from velab.config import load_material, load_rig
    from velab.model import valve_head

    rig = load_rig("perugia")
    t = np.arange(2000) / 1000.0
    h = valve_head(t, rig, load_material("A"))
    return fit_sweep(t, h, rig, models=range(4), window_s=None, starts=2, polish=False)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--rate", type=float, default=10000.0)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    from velab.runfiles import save_fit

    result = a_fit()
    with tempfile.TemporaryDirectory(dir=".") as d:
        run = Path(d) / "run.h5"
        make_run(run, args.rate, args.minutes * 60)
        size = run.stat().st_size / 2**20
        saves, copies, synced = [], [], []
        for i in range(args.repeat):
            t0 = time.perf_counter()
            shutil.copyfile(run, Path(d) / "plain.h5")
            copies.append(time.perf_counter() - t0)
            with open(Path(d) / "plain.h5", "rb+") as fh:
                os.fsync(fh.fileno())
            synced.append(time.perf_counter() - t0)
            (Path(d) / "plain.h5").unlink()
            t0 = time.perf_counter()
            save_fit(run, result, f"bench{i}")
            saves.append(time.perf_counter() - t0)
        s, c, f = min(saves), min(copies), min(synced)
        print(f"run file {size:.0f} MiB ({args.minutes:g} min at {args.rate:g} Hz, 7 fast channels)")
        print(f"save_fit (atomic copy + fsync + rename): {s:.3f} s")
        print(f"baselines: plain copy {c:.3f} s (ratio {s / c:.2f}), copy + fsync {f:.3f} s (ratio {s / f:.2f})")


if __name__ == "__main__":
    main()
