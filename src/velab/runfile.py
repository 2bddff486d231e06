"""Deprecated: the run-file API is :mod:`velab.runfiles` (import from its modules).

Left only while callers outside the recorder still import it (velab.commands.fit,
velab.commands.import_csv, velab.gui.archive_io, some tests and benchmarks); delete it with the last.
"""

from velab.runfiles import *  # noqa: F401,F403
from velab.runfiles import __all__  # noqa: F401
