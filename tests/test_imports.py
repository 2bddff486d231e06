"""Import hygiene: every module imports on its own in a fresh interpreter (an import cycle that only
works in one order is caught), and the device layer stays below the application.

Function-level imports that dodge a cycle are not allowed (issue 11): a cycle hidden that way
breaks a standalone import sooner or later. Lazy imports of heavy libraries for start-up speed
(the CLI's command modules) are fine and do not show here.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"velab": ROOT / "src" / "velab", "velab.drivers": ROOT / "drivers", "velab.simulators": ROOT / "simulators"}


def modules(package: str) -> list[str]:
    base = PACKAGES[package]
    out = []
    for f in sorted(base.rglob("*.py")):
        rel = f.relative_to(base).with_suffix("")
        parts = [p for p in rel.parts if p != "__init__"]
        out.append(".".join([package, *parts]))
    return out


ALL = modules("velab") + modules("velab.drivers") + modules("velab.simulators")
DEVICE_LAYER = modules("velab.drivers") + modules("velab.simulators")


# One interpreter per module, made cheap: a parent imports the third-party libraries velab uses (never
# a velab module), then forks a child per module, which imports that one module into a sys.modules that
# holds no velab module: for velab's own imports this is a fresh interpreter, at a fork's cost.
_FORKER = r"""
import ast, importlib, os, sys
from pathlib import Path
names, files = sys.argv[1].split(","), sys.argv[2:]
third = set()
for f in files:
    for node in ast.walk(ast.parse(Path(f).read_text())):
        if isinstance(node, ast.Import):
            third.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            third.add(node.module)
for lib in sorted(t for t in third if t.split(".")[0] != "velab"):
    try:
        importlib.import_module(lib)
    except Exception:
        pass
assert not [m for m in sys.modules if m == "velab" or m.startswith("velab.")], "a library imported velab"
bad, running = 0, set()
for name in names + [None, None]:
    if len(running) == 2 or (name is None and running):  # two children at a time (two cores)
        pid, status = os.wait()
        running.discard(pid)
        bad += os.waitstatus_to_exitcode(status) != 0
    if name is None:
        continue
    pid = os.fork()
    if pid == 0:
        try:
            importlib.import_module(name)
        except BaseException as exc:
            sys.stderr.write(f"{name}: {type(exc).__name__}: {exc}\n")
            sys.stderr.flush()
            os._exit(1)
        os._exit(0)
    running.add(pid)
sys.exit(1 if bad else 0)
"""


@pytest.mark.timeout(600)
def test_every_module_imports_alone_in_a_fresh_interpreter():
    assert len(ALL) > 100 and "velab.recording.engine" in ALL and "velab.simulators.bench" in ALL
    files = [str(f) for base in PACKAGES.values() for f in sorted(base.rglob("*.py"))]
    p = subprocess.run([sys.executable, "-c", _FORKER, ",".join(ALL), *files], capture_output=True, text=True,
                       timeout=500)
    assert p.returncode == 0, p.stderr


def test_device_layer_does_not_import_the_application():
    code = (f"import sys\nfor m in {DEVICE_LAYER!r}:\n    __import__(m)\n"
            "print(' '.join(sorted(m for m in sys.modules if m.startswith('velab.'))))")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    loaded = p.stdout.split()
    assert "velab.simulators.bench" in loaded and "velab.drivers.streaming_adc" in loaded  # the code above ran
    heavy = [m for m in loaded if m.split(".")[1] in ("recording", "fitting", "gui", "commands", "runfiles")]
    assert not heavy, heavy


# What the processes that never fit import (issue 51, start-up): the recorder with the simulated rig (its commands
# and engine), velab synth, the catalogue extractor's child and the run-file reader, and the stored fit's
# presentation: no scipy (the model transforms with numpy.fft) and none of the fitter's scipy modules (the
# recorder takes the fit path's light policy modules, velab.fitting.options and window; a stored fit's
# results and presentation are numpy only). The fit path itself does not import scipy.signal (velab.filters),
# whose import pulls in scipy.stats (~1.5 s).
_LOADED = "import importlib, sys\nfor m in sys.argv[1:]:\n    importlib.import_module(m)\nprint(' '.join(sys.modules))"
NEVER_FIT = ["velab.commands.record", "velab.recording", "velab.simulators.bench", "velab.synth", "velab.commands.synth",
             "velab.catalogue.extract", "velab.catalogue.rows", "velab.runfiles.reader", "velab.fitting.results",
             "velab.fitting.headline", "velab.fitting.report", "velab.fitservice.request"]
FITTER = {"velab.fitting.friction", "velab.fitting.sweep", "velab.fitting.prepare", "velab.fitting.entry",
          "velab.fitting.flows", "velab.fitting.solvers", "velab.fitting.data", "velab.fitting.refine"}


def _loaded(modules: list[str]) -> set[str]:
    p = subprocess.run([sys.executable, "-c", _LOADED, *modules], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    return set(p.stdout.split())


def test_the_processes_that_never_fit_import_neither_scipy_nor_the_fitter():
    loaded = _loaded(NEVER_FIT)
    assert "velab.recording.engine" in loaded and "velab.simulators.rig" in loaded  # the code above ran
    assert not [m for m in loaded if m == "scipy" or m.startswith("scipy.")]
    assert not loaded & FITTER
    assert "numba" not in loaded  # the MOC's kernel is loaded when a transient is computed, not at import


FIT_PATH = ["velab.fitting.entry", "velab.fitservice.execute", "velab.fit_worker", "velab.fitting.joint",
            "velab.fitting.sweep", "velab.commands.fit"]


@pytest.fixture(scope="module")
def fit_path_loaded() -> set[str]:
    """The fit path's modules imported in one fresh interpreter; the two tests below only read what it loaded."""
    return _loaded(FIT_PATH)


def test_the_fit_path_does_not_import_scipy_signal(fit_path_loaded):
    loaded = fit_path_loaded
    assert "velab.fitting.prepare" in loaded and "velab.filters" in loaded
    assert not [m for m in loaded if m.startswith(("scipy.signal", "scipy.stats"))]


# scipy.optimize (~0.2-0.4 s of start-up, with scipy.sparse, scipy.spatial, scipy.constants) is imported by the
# options that use it only (--method nelder-mead, evolution; Brunone's friction): a default fit's one scipy.optimize
# call, the equivalent friction's bounded search, is velab.fitting.bounded (scipy's steps: tests/fitting/test_bounded.py)
def test_the_fit_path_does_not_import_scipy_optimize(fit_path_loaded):
    loaded = fit_path_loaded
    assert "velab.fitting.friction" in loaded and "velab.fitting.solvers" in loaded
    assert not [m for m in loaded if m.startswith(("scipy.optimize", "scipy.sparse", "scipy.spatial"))]


_FIT_LOADED = r"""
import sys, tempfile
from pathlib import Path
from velab.cli import main
p = str(Path(tempfile.mkdtemp()) / "q.h5")
assert main(["synth", "--rate", "200", "--duration", "3", "-o", p, "-q"]) == 0  # quadratic friction: the MOC
assert main(["fit", p, "--models", "0-1", "--window", "3", "--no-save", "-q"]) == 0
print(" ".join(sys.modules))
"""


@pytest.mark.timeout(300)
def test_a_default_fit_does_not_import_scipy_optimize():
    """The default fit of a quadratic-friction record (the equivalent friction's search runs) in a fresh process."""
    p = subprocess.run([sys.executable, "-c", _FIT_LOADED], capture_output=True, text=True, timeout=280)
    assert p.returncode == 0, p.stderr
    loaded = set(p.stdout.split())
    assert "velab.fitting.bounded" in loaded and "velab.moc.kernel" in loaded  # the fit ran, with the MOC
    assert not [m for m in loaded if m.startswith(("scipy.optimize", "scipy.sparse", "scipy.spatial"))]
