"""Compatibility module: the run-file API moved to the :mod:`velab.runfiles` package.

Kept so that ``from velab.runfile import read_run, RunWriter, ...`` (recorder,
GUI, benchmarks, tests) keeps working; new code imports :mod:`velab.runfiles`.
"""

import contextlib

from velab.runfiles import *  # noqa: F401,F403
from velab.runfiles import __all__ as _all
from velab.runfiles.atomic import edit_copy
from velab.runfiles.layout import to_str as _str  # noqa: F401 - used by older callers

__all__ = list(_all) + ["fits_group"]


@contextlib.contextmanager
def fits_group(path):
    """``/entry/fits`` of a copy of the run, opened read-write; the copy replaces the run on success (atomic)."""
    with edit_copy(path) as fh:
        e = fh["entry"]
        if "fits" not in e:
            e.create_group("fits").attrs["NX_class"] = "NXcollection"
        yield e["fits"]
