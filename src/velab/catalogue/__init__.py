"""The run catalogue: every run under some folders, one row each, kept fast by an SQLite index.

Modules: :mod:`~velab.catalogue.rows` (one run file -> one row, read only),
:mod:`~velab.catalogue.extract` (rows read in worker processes under a deadline),
:mod:`~velab.catalogue.index` (the SQLite catalogue in the user's cache, updated by
path, size, mtime), :mod:`~velab.catalogue.liveness` (a ``recording`` run: live, or its
recorder died), :mod:`~velab.catalogue.query` (filters, sort, table and CSV).

Light on purpose: ``velab --help`` imports nothing from here; h5py only in the workers.
"""

from __future__ import annotations

RUN_SUFFIXES = (".h5", ".hdf5", ".nxs")
