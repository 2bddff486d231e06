"""Start-up time of the CLI: ``velab --help`` (target < 0.2 s) against a bare ``python -c pass``.

Run as ``python benchmarks/cli_startup.py [--repeats N]``. Each command is run in a fresh
interpreter (subprocess, as a user's shell would), alternating the two so that both see
the same machine load; the figure is the median wall time, and the ratio to the bare
interpreter's median in the same run is what to compare across machines. Also printed:
the heaviest imports of ``velab --help`` (``python -X importtime``) and whether numpy,
scipy, h5py, matplotlib or Qt were imported at all (they must not be).
No assertions: timings depend on the machine.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import sys
import time

HEAVY = ("numpy", "scipy", "h5py", "matplotlib", "PySide6", "pyqtgraph", "pymodbus", "serial")
COMMANDS = {
    "python -c pass": [sys.executable, "-c", "pass"],
    "velab --help": [sys.executable, "-m", "velab.cli", "--help"],
    "velab fit --help": [sys.executable, "-m", "velab.cli", "fit", "--help"],
    "velab --version": [sys.executable, "-m", "velab.cli", "--version"],
}


def wall(cmd: list[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
    return time.perf_counter() - t0


def import_profile() -> tuple[list[tuple[int, str]], list[str]]:
    """(cumulative us, module) of the slowest top-level imports, and the heavy packages imported."""
    out = subprocess.run([sys.executable, "-X", "importtime", "-m", "velab.cli", "--help"],
                         capture_output=True, text=True, check=True).stderr
    rows, heavy = [], set()
    for line in out.splitlines():
        if not line.startswith("import time:") or "|" not in line or "cumulative" in line:
            continue
        _, cumulative, name = line[len("import time:"):].split("|")
        module = name.strip()
        rows.append((int(cumulative), module))
        root = module.split(".")[0]
        if root in HEAVY:
            heavy.add(root)
    rows.sort(reverse=True)
    return rows[:8], sorted(heavy)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=15)
    n = ap.parse_args().repeats
    for cmd in COMMANDS.values():  # warm the OS caches once
        wall(cmd)
    times: dict[str, list[float]] = {k: [] for k in COMMANDS}
    for _ in range(n):
        for name, cmd in COMMANDS.items():
            times[name].append(wall(cmd))
    base = statistics.median(times["python -c pass"])
    print(f"# CLI start-up, {platform.python_implementation()} {platform.python_version()}, "
          f"{os.cpu_count()} CPUs, {n} runs each, median wall time")
    print(f"{'command':<20}{'median (s)':>12}{'min (s)':>10}{'ratio to python -c pass':>26}")
    for name, ts in times.items():
        med = statistics.median(ts)
        print(f"{name:<20}{med:>12.3f}{min(ts):>10.3f}{med / base:>26.2f}")
    help_s = statistics.median(times["velab --help"])
    print(f"velab --help: {help_s:.3f} s ({'meets' if help_s < 0.2 else 'MISSES'} the 0.2 s target), "
          f"{help_s / base:.2f} x a bare interpreter, {help_s - base:.3f} s of velab's own")
    top, heavy = import_profile()
    print("heaviest imports of velab --help (cumulative ms): "
          + ", ".join(f"{m} {us / 1000:.1f}" for us, m in top))
    print("heavy packages imported by velab --help: " + (", ".join(heavy) if heavy else "none"))


if __name__ == "__main__":
    main()
