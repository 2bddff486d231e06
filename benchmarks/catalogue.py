"""The run catalogue on a large archive: first indexing, a listing from the index, one run added,
and the Archive tab's first paint, each with its ratio to a baseline measured in the same run.

    python benchmarks/catalogue.py [--runs 10000] [--jobs 2] [--keep DIR]

The archive is N copies of one small fitted synthetic run (1 s at 200 Hz, EL..S1 fitted) in
nested dated folders. Baseline: a plain directory walk plus an h5py open and close of every
file in one process (what any listing that looks into the files costs at the least).

``--keep DIR`` keeps the archive and its index there, and reuses them when they are already
there (the first indexing is then what the kept index leaves to read). The commands run with
their bytecode cached (``PYTHONPYCACHEPREFIX`` in DIR, ``PYTHONDONTWRITEBYTECODE`` dropped), as
an installed package has it: a development shell that forbids .pyc files would otherwise add
the compilation of ~45 modules (0.3 s) to every command.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def velab(*args, env=None) -> tuple[float, subprocess.CompletedProcess]:
    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-m", "velab.cli", *map(str, args)], capture_output=True, text=True,
                         env=env)
    if out.returncode != 0:
        raise SystemExit(f"velab {' '.join(map(str, args))} failed: {out.stderr.strip()}")
    return time.perf_counter() - t0, out


def make_archive(root: Path, n: int) -> Path:
    src = root / "source.h5"
    velab("synth", "--material", "A", "--duration", "1", "--rate", "200", "-o", src, "-q")
    velab("fit", src, "--models", "0-1", "--window", "0.9", "--starts", "1", "-q")
    arch = root / "archive"
    for i in range(n):
        d = arch / f"2026-{1 + i * 12 // n:02d}" / f"day{i % 28:02d}"
        d.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(src, d / f"run{i:05d}.h5")
    (arch / "broken.h5").write_bytes(b"not an HDF5 file")
    return src


def baseline(arch: Path) -> float:
    import h5py

    t0 = time.perf_counter()
    n = 0
    for d, _, files in os.walk(arch):
        for f in files:
            if f.endswith(".h5"):
                try:
                    with h5py.File(os.path.join(d, f), "r", locking=False):
                        n += 1
                except OSError:
                    pass
    return time.perf_counter() - t0


def gui_first_paint(arch: Path, env: dict) -> tuple[float, float]:
    """Seconds to the first painted table of the Archive tab from the index, and the longest GUI stall."""
    code = f"""
import os, sys, time
os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
from PySide6.QtCore import QTimer
from velab.gui.app import ensure_app
from velab.gui.main_window import MainWindow, make_settings
app = ensure_app()
win = MainWindow(settings=make_settings({str(arch.parent / 'gui.ini')!r}))
win.resize(1366, 768); win.show(); win.tabs.setCurrentWidget(win.archive)
app.processEvents()
a = win.archive
stalls, last = [], [time.perf_counter()]
def tick():
    now = time.perf_counter(); stalls.append(now - last[0]); last[0] = now
timer = QTimer(); timer.setInterval(5); timer.timeout.connect(tick); timer.start()
done = []
a.indexed.connect(done.append)
t0 = time.perf_counter()
a.set_folder({str(arch)!r})
first = None
while not done:
    app.processEvents()
    if first is None and a.catalogue.model.rowCount():
        a.catalogue.table.viewport().repaint()
        first = time.perf_counter() - t0
    time.sleep(0.001)
print(first, max(stalls))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=600)
    if out.returncode:
        raise SystemExit(f"GUI measurement failed: {out.stderr.strip()[-500:]}")
    first, stall = out.stdout.split()[-2:]
    return float(first), float(stall)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=10_000)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--keep", help="make the archive in this folder and keep it")
    args = ap.parse_args()
    root = Path(args.keep or tempfile.mkdtemp(prefix="velab-catalogue-"))
    root.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, VELAB_CATALOGUE=str(root / "index.sqlite"), PYTHONPYCACHEPREFIX=str(root / "pycache"))
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    try:
        t0 = time.perf_counter()
        arch = root / "archive"
        src = root / "source.h5"
        reused = args.keep and src.is_file() and arch.is_dir()
        if reused:
            for p in arch.rglob("added*.h5"):  # a previous run's addition
                p.unlink()
            args.runs = sum(1 for p in arch.rglob("run*.h5"))
        else:
            make_archive(root, args.runs)
        print(f"archive: {args.runs} runs + 1 damaged file {'reused' if reused else 'made'} in "
              f"{time.perf_counter() - t0:.1f} s; {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}")
        velab("--help", env=env)  # compile the bytecode once, as an installation does
        subprocess.run([sys.executable, "-c", "import velab.catalogue.rows, velab.runfiles.reader"], env=env,
                       check=True)
        base = baseline(arch)
        print(f"baseline (walk + h5py open/close of every file, 1 process): {base:.2f} s")
        first, out = velab("runs", arch, "--json", "--jobs", args.jobs, env=env)
        doc = json.loads(out.stdout)
        assert len(doc["runs"]) == args.runs + 1, len(doc["runs"])
        print(f"first indexing (velab runs --json, {args.jobs} jobs): {first:.2f} s = {first / base:.2f} x baseline, "
              f"{first / args.runs * 1e3:.2f} ms per run")
        again = min(velab("runs", arch, "--json", env=env)[0] for _ in range(3))
        print(f"listing with the index (nothing changed, --json of {args.runs} rows): {again:.3f} s "
              f"(target < 1 s) = {again / base:.3f} x baseline")
        table = min(velab("runs", arch, "--best", "S1", "--since", "2026-06-01", "--text", "material", env=env)[0]
                    for _ in range(3))
        print(f"filtered listing with the index (text table; the copies all match: {args.runs} lines): {table:.3f} s")
        few = min(velab("runs", arch, "--status", "damaged", "--q0", "1:", env=env)[0] for _ in range(3))
        print(f"selective filter with the index (text table, no line): {few:.3f} s = {few / base:.3f} x baseline")
        shutil.copyfile(src, arch / "2026-12" / "added.h5")
        added, out = velab("runs", arch, "--json", env=env)
        doc = json.loads(out.stdout)
        assert doc["index"]["read"] == 1 and any(r["path"].endswith("added.h5") for r in doc["runs"])
        print(f"listing after adding one run (read 1 file): {added:.3f} s (target < 1 s)")
        try:
            import PySide6  # noqa: F401
        except ImportError:
            print("GUI: PySide6 not installed, not measured")
            return
        (arch.parent / "gui.ini").unlink(missing_ok=True)  # a kept one reopens the folder at start: a second load
        paint, stall = gui_first_paint(arch, env)
        print(f"Archive tab: first paint from the index {paint:.3f} s, longest GUI-thread stall while "
              f"{args.runs} rows load {stall * 1e3:.0f} ms (target < 250 ms)")
    finally:
        if not args.keep:
            shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
