"""``velab recover``: a closed, complete copy of a run whose writer died.

The original is only read. The copy is the original's bytes with the
superblock's "open for write" flags cleared (what ``h5clear -s`` does), then,
opened normally: every fast channel cut to one common length (a killed writer
may leave one a flush ahead), ``end_time`` set to the last instant the
writer wrote, and a ``status_reason`` saying where it came from. Its status
stays ``recording`` (the run is incomplete) unless the run had been concluded.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import h5py
import numpy as np

from velab.errors import DataError
from velab.runfiles import layout as L
from velab.runfiles import superblock as sb_
from velab.runfiles.atomic import _copy
from velab.runfiles.probe import trust
from velab.runfiles.reader import read_run


def recover_run(src: str | os.PathLike, dst: str | os.PathLike | None = None) -> tuple[Path, int]:
    """Write ``dst`` (default ``NAME.recovered.h5``), a closed copy of ``src``; returns (copy, samples)."""
    src = Path(src)
    dst = Path(dst) if dst is not None else src.with_name(f"{src.stem}.recovered{src.suffix}")
    run = read_run(src)  # a DataError here: nothing readable to recover
    if not run.open_for_write and not run.incomplete:
        raise DataError(f"{src}: nothing to recover: the run was closed ({run.status})")
    if dst.exists():
        raise DataError(f"{dst}: already exists; a run file is never overwritten")
    if not dst.parent.is_dir():
        raise DataError(f"{dst.parent}: output directory does not exist")
    tmp = dst.with_name(f".{dst.name}.part")
    tmp.unlink(missing_ok=True)
    try:
        _copy(src, tmp)
        sb = sb_.read_superblock(tmp)
        if sb.open_for_write:
            sb_.clear_status_flags(tmp)
        if sb.eoa is not None and os.path.getsize(tmp) < sb.eoa:
            os.truncate(tmp, sb.eoa)  # space the writer had allocated but not yet written (h5clear -i)
        with h5py.File(tmp, "r+", locking=False) as fh:
            _close_entry(fh, src, run)
        trust(tmp)  # made from a file already walked (read_run above)
        n = read_run(tmp).n_samples  # the copy must read back
        os.replace(tmp, dst)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if isinstance(exc, (OSError, KeyError, ValueError, RuntimeError)):
            raise DataError(f"{src}: cannot be recovered ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
        raise
    return dst, n


def _close_entry(fh: h5py.File, src: Path, run) -> None:
    e = fh["entry"]
    data = e["data"]
    axis = L.to_str(np.atleast_1d(data.attrs.get("axes", ["time"]))[0])
    signal = L.to_str(data.attrs.get("signal", "head"))
    n = min(data[axis].shape[0], data[signal].shape[0])
    for ds in data.values():  # one sample count for every fast channel (hard links: the same objects)
        if isinstance(ds, h5py.Dataset) and ds.maxshape == (None,) and ds.shape[0] > n:
            ds.resize((n,))
    if not run.incomplete:
        return  # a closed run flagged only by a killed in-place save: its facts are right as they are
    if not run.end_time:
        L.set_str(e, "end_time", _last_write_time(src, data, n))
    if not run.status_reason:
        L.set_str(e, "status_reason", f"recovered copy of {src.name} (its writer never closed it; "
                                      "end_time is its last write)")


def _last_write_time(src: Path, data: h5py.Group, n: int) -> str:
    """When the writer last wrote: the host clock of the last sample if recorded, else the file's mtime."""
    if "host_time" in data and n > 0:
        t = float(data["host_time"][n - 1])
        if np.isfinite(t) and t > 0:
            return L.iso_of(t)
    return L.iso_of(os.stat(src).st_mtime)
