"""velab.fitting and velab.fitservice name their API at the package and import it on first use (velab.lazy):
importing the package loads none of its modules (no numpy, no scipy), reading a name loads the one module
that defines it, and ``dir()`` lists every exported name."""

from __future__ import annotations

import subprocess
import sys

_CHILD = r"""
import sys
import velab.fitting, velab.fitservice
print(sorted(m for m in sys.modules if m.split(".")[0] in ("velab", "numpy", "scipy")))
assert {"fit_run", "fit_sweep", "FitOptions", "format_report"} <= set(dir(velab.fitting)), dir(velab.fitting)
assert {"FitService", "FitRequest", "RunFiles"} <= set(dir(velab.fitservice)), dir(velab.fitservice)
# (execute is not a package name: once its module is imported, the package's attribute is that module)
import velab.fitservice.execute
from velab.fitservice.execute import execute
assert callable(execute) and "execute" not in velab.fitservice.__all__
from velab.fitservice import FitRequest
from velab.fitservice.request import FitRequest as direct
assert FitRequest is direct and "velab.fitservice.service" not in sys.modules
from velab.fitting import FitOptions
import velab.fitting.options
assert FitOptions is velab.fitting.options.FitOptions and "FitOptions" in vars(velab.fitting)
assert "scipy" not in sys.modules and "velab.fitting.entry" not in sys.modules
try:
    velab.fitting.fit_nothing
except AttributeError as exc:
    assert str(exc) == "module 'velab.fitting' has no attribute 'fit_nothing'", exc
else:
    raise AssertionError("an unknown name was found")
from velab.fitting import fit_run
import velab.fitting.entry
assert fit_run is velab.fitting.entry.fit_run
"""


def test_the_packages_are_light_and_their_names_are_found_on_first_use():
    out = subprocess.run([sys.executable, "-c", _CHILD], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines()[0] == str(["velab", "velab.errors", "velab.fitservice", "velab.fitting",
                                              "velab.lazy", "velab.version"])
