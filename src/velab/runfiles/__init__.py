"""velab run files: one HDF5 file per water-hammer run, in a light NeXus layout (docs/run-format.md).

Public API::

    from velab.runfiles import read_run, open_run_file, RunWriter, write_run, save_fit, recover_run
    run = read_run("runs/a.h5")                # Run; one-line DataError for anything wrong
    save_fit("runs/a.h5", result, "online")     # atomic: copy, write /entry/fits/online, rename
    recover_run("runs/killed.h5")               # closed copy of a run whose writer died

Modules: :mod:`~velab.runfiles.layout` (names, types, units), :mod:`~velab.runfiles.writer`,
:mod:`~velab.runfiles.reader`, :mod:`~velab.runfiles.h5open` (opening any file without a hang),
:mod:`~velab.runfiles.superblock`, :mod:`~velab.runfiles.atomic` (copy-and-rename edits, lock),
:mod:`~velab.runfiles.fits` (fit groups), :mod:`~velab.runfiles.recover`.
"""

from velab.runfiles.fits import default_fit_name, read_fit_dict, read_fit_group, save_fit, validate_fit_name, write_fit_group
from velab.runfiles.h5open import RunStillOpen
from velab.runfiles.layout import FILE_FORMAT, FORMAT_VERSION, STATUSES, now_iso
from velab.runfiles.reader import Run, open_run_file, read_run
from velab.runfiles.recover import recover_run
from velab.runfiles.writer import DEFAULT_CHANNELS, HEAD, Channel, RunWriter, software_versions, write_run

__all__ = [
    "Run", "RunStillOpen", "open_run_file", "read_run", "RunWriter", "Channel", "HEAD", "DEFAULT_CHANNELS",
    "write_run", "save_fit", "read_fit_group", "read_fit_dict", "write_fit_group", "default_fit_name",
    "validate_fit_name", "recover_run", "software_versions", "FILE_FORMAT", "FORMAT_VERSION", "STATUSES", "now_iso",
]
