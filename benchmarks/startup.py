"""Start-up of velab's real processes (issue 51): the CPU and wall time their imports take, before and after.

Run as ``python benchmarks/startup.py [--before PYTHON] [--repeats N] [--only COMMAND ...]``: this interpreter runs this checkout's
velab ("after"); ``--before`` another one's (say a checkout of main with its own venv: ``.venv/bin/python``).
Each command runs in a fresh interpreter, the two versions in turn so that both see the same machine load:

* ``fit``: ``velab fit a.h5 --no-save`` on ``velab synth --material A`` (the whole fit runs; its imports counted);
* ``record``: ``velab record --simulate --fast --no-fit --duration 1``, counted up to the "armed" phase line;
* ``extractor``: the catalogue's fresh child (``python -m velab.catalogue.extract``) reading two run files;
* ``synth``: ``velab synth --material A``.

The command runs in-process under a small driver that times every outermost import (``builtins.__import__`` and
``importlib.import_module``, per thread: CPU by ``time.thread_time``, wall by ``perf_counter``); the process's
own CPU (user + system, interpreter start included, and its reaped children's: the reader's probe child) comes
from ``os.wait4``; the wall time spent waiting for the probe child (velab.runfiles.probe's select) is summed too.
Printed: medians over the repeats, the ratio after / before of each, and which heavy modules each version
imported. No assertions: timings depend on the machine; the ratios are what to compare.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HEAVY = ("scipy.signal", "scipy.stats", "scipy.fft", "scipy.optimize", "scipy.sparse", "scipy.linalg", "scipy", "numba",
         "velab.fitting.friction")

# runs in the child: argv = [result file, mode, module, mark or "", args...]
DRIVER = r"""
import builtins, importlib, json, os, runpy, sys, threading, time
out_path, module, mark, args = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4:]
local = threading.local()
tot = {"cpu": 0.0, "wall": 0.0}
at_mark = {}
lock = threading.Lock()

def timed(fn):
    def wrapper(*a, **k):
        depth = getattr(local, "depth", 0)
        if depth:
            local.depth = depth + 1
            try:
                return fn(*a, **k)
            finally:
                local.depth = depth
        local.depth = 1
        c0, w0 = time.thread_time(), time.perf_counter()
        try:
            return fn(*a, **k)
        finally:
            local.depth = 0
            with lock:
                tot["cpu"] += time.thread_time() - c0
                tot["wall"] += time.perf_counter() - w0
    return wrapper

builtins.__import__ = timed(builtins.__import__)
importlib.import_module = timed(importlib.import_module)

# the wall time this process waits for the reader's probe child (velab.runfiles.probe: its select on the child)
import select
probe_wait = [0.0]
_select = select.select

def timed_select(*a, **k):
    if not sys._getframe(1).f_code.co_filename.endswith("probe.py"):
        return _select(*a, **k)
    w0 = time.perf_counter()
    try:
        return _select(*a, **k)
    finally:
        probe_wait[0] += time.perf_counter() - w0

select.select = timed_select

class Watch:
    def __init__(self, stream):
        self.stream = stream
    def write(self, text):
        if mark and not at_mark and mark in text:
            at_mark.update(import_cpu=tot["cpu"], import_wall=tot["wall"], cpu=time.process_time(),
                           wall=time.perf_counter() - t0)
        return self.stream.write(text)
    def __getattr__(self, name):
        return getattr(self.stream, name)

t0 = time.perf_counter()
sys.stdout, sys.stderr = Watch(sys.stdout), Watch(sys.stderr)
sys.argv = [module] + args
code = 0
try:
    runpy.run_module(module, run_name="__main__", alter_sys=True)
except SystemExit as exc:
    code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
res = {"import_cpu": tot["cpu"], "import_wall": tot["wall"], "wall": time.perf_counter() - t0, "code": code,
       "probe_wait": probe_wait[0],
       "modules": sorted(m for m in sys.modules if m.startswith(("scipy", "numba", "velab.fitting.friction"))),
       "mark": at_mark}
with open(out_path, "w") as f:
    json.dump(res, f)
"""


def run(python: str, module: str, args: list[str], mark: str = "", stdin: bytes | None = None) -> dict:
    """One fresh process: the driver's figures and the process's CPU (os.wait4)."""
    with tempfile.NamedTemporaryFile(suffix=".json", delete=False) as f:
        out = f.name
    try:
        # bytecode written and read (PYTHONDONTWRITEBYTECODE dropped), as an installed package has it: a version
        # without its .pyc files would spend its start-up compiling the sources
        env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
        proc = subprocess.Popen([python, "-c", DRIVER, out, module, mark, *args], stdin=subprocess.PIPE,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
        if stdin is not None:
            proc.stdin.write(stdin)
        proc.stdin.close()
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        res = json.loads(Path(out).read_text())
    finally:
        os.unlink(out)
    if proc.returncode != 0 or res["code"] != 0:
        raise RuntimeError(f"{python} {module} {' '.join(args)} exited {proc.returncode} ({res['code']})")
    res["cpu"] = usage.ru_utime + usage.ru_stime
    return res


def heavy_of(modules: list[str]) -> str:
    names = set(modules)
    shown = [h for h in HEAVY if h in names]
    # "scipy" alone only when none of its subpackages listed says it already
    if any(h.startswith("scipy.") for h in shown) and "scipy" in shown:
        shown.remove("scipy")
    return ", ".join(shown) or "none"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", help="the interpreter of the version to compare with (its own venv)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--only", nargs="+", choices=("fit", "record", "extractor", "synth"), help="these commands only")
    opts = ap.parse_args()
    versions = {"after": sys.executable}
    if opts.before:
        versions = {"before": opts.before, **versions}
    tmp = Path(tempfile.mkdtemp(prefix="velab-startup-"))
    a = tmp / "a.h5"
    subprocess.run([sys.executable, "-m", "velab.cli", "synth", "--material", "A", "-o", str(a)], check=True,
                   capture_output=True)
    recs = tmp / "runs"
    subprocess.run([sys.executable, "-m", "velab.cli", "record", "--simulate", "--fast", "--no-fit", "--duration",
                    "1", "--out-dir", str(recs)], check=True, capture_output=True)
    files = [str(a)] + sorted(str(p) for p in recs.glob("*.h5"))
    paths = "".join(json.dumps(p) + "\n" for p in files).encode()
    commands = {
        "fit": ("velab.cli", ["fit", str(a), "--no-save"], "", None),
        "record": ("velab.cli", ["record", "--simulate", "--fast", "--no-fit", "--duration", "1", "--out-dir",
                                 str(tmp / "bench-runs")], "] armed", None),
        "extractor": ("velab.catalogue.extract", [], "", paths),
        "synth": ("velab.cli", ["synth", "--material", "A", "-o", str(tmp / "s.h5"), "--force"], "", None),
    }
    commands = {c: v for c, v in commands.items() if not opts.only or c in opts.only}
    for py in versions.values():  # warm the OS caches and numba's disk cache once per version
        for module, args, mark, stdin in commands.values():
            run(py, module, args, mark, stdin)
    results: dict = {(c, v): [] for c in commands for v in versions}
    for _ in range(opts.repeats):
        for c, (module, args, mark, stdin) in commands.items():
            for v, py in versions.items():
                results[c, v].append(run(py, module, args, mark, stdin))
    load = os.getloadavg()
    print(f"# start-up of velab's processes, {platform.python_implementation()} {platform.python_version()}, "
          f"{os.cpu_count()} CPUs, load {load[0]:.1f}, {opts.repeats} runs each, medians (s)")
    cols = ["imports cpu", "imports wall", "process cpu", "process wall", "probe wait"]
    print(f"{'command':<11}{'version':<8}" + "".join(f"{c:>14}" for c in cols) + "   heavy modules imported")
    for c, (_, _, mark, _) in commands.items():
        med = {}
        for v in versions:
            rs = results[c, v]
            if mark:  # up to the mark: the record's imports and CPU until it is armed
                vals = [[r["mark"]["import_cpu"], r["mark"]["import_wall"], r["mark"]["cpu"], r["mark"]["wall"],
                         r["probe_wait"]] for r in rs]
            else:
                vals = [[r["import_cpu"], r["import_wall"], r["cpu"], r["wall"], r["probe_wait"]] for r in rs]
            med[v] = [statistics.median(x) for x in zip(*vals)]
            print(f"{c:<11}{v:<8}" + "".join(f"{x:>14.3f}" for x in med[v]) + "   " + heavy_of(rs[-1]["modules"]))
        if "before" in med:
            print(f"{'':<11}{'ratio':<8}" + "".join(f"{x / y:>14.2f}" if y > 0 else f"{'-':>14}"
                                                    for x, y in zip(med["after"], med["before"])))
    print("record: up to its 'armed' line (process cpu: the process's CPU by then; wall: from the command's "
          "start); the others to their end; fit: the whole fit, its imports wherever they happen; probe wait: "
          "the wall time waiting for the child that walks a run file before it is read (velab.runfiles.probe; "
          "its start-up, then its walk)")


if __name__ == "__main__":
    main()
