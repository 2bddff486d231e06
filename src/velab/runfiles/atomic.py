"""Atomic edits of a run file: work on a copy, then rename it over the run.

The run is never opened for writing. :func:`edit_copy` takes the run's lock,
copies the file beside it (same directory, hidden temporary name), lets the
caller change the copy, fsyncs it and ``os.replace``-s it over the run, then
fsyncs the directory. A kill at any instant leaves either the old file or the
new one under the run's name, both complete; a killed edit leaves at most a
hidden ``.NAME.h5.<pid>.edit.part`` that the next edit of that run removes.

Why a copy rather than a sidecar file: the fits travel with the run when
archives are copied around; a reader holding the file open keeps reading the
old, consistent version (POSIX); the price is one copy of the file per save
(``os.copy_file_range``, a reflink on btrfs/xfs), measured in
benchmarks/fit_save.py.

Test hook: with ``VELAB_TEST_PAUSE_AT=<stage>`` (or ``<stage>:<seconds>``) in the
environment, the edit prints ``velab-stage <stage>`` on stderr at that stage and
sleeps (an hour, or the seconds given), so a test can kill the process exactly
there, or hold the lock while another process waits (stages: :data:`STAGES`).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Iterator

import h5py

from velab.errors import DataError
from velab.runfiles import layout as L
from velab.runfiles.h5open import RunStillOpen, check_file, open_h5
from velab.runfiles.soundness import defects, describe_defects
from velab.runfiles.probe import trust

try:
    import fcntl
except ImportError:  # Windows: no advisory locks; concurrent saves are then not serialised
    fcntl = None

STAGE_ENV = "VELAB_TEST_PAUSE_AT"
STAGES = ("locked", "copying", "copied", "writing", "written", "closed", "synced", "replaced", "done")
LOCK_TIMEOUT_S = 60.0
_FIRST_BLOCK = 1 << 20  # small, so that `copying` is an instant of a test's copy
_COPY_BLOCK = 256 << 20


def stage(name: str) -> None:
    """A named instant of an edit; the test hook pauses here (see the module docstring)."""
    hook = os.environ.get(STAGE_ENV)
    if hook and hook.split(":")[0] == name:
        sys.stderr.write(f"velab-stage {name}\n")
        sys.stderr.flush()
        time.sleep(float(hook.split(":")[1]) if ":" in hook else 3600.0)


@contextlib.contextmanager
def run_lock(path: Path, timeout_s: float = LOCK_TIMEOUT_S) -> Iterator[None]:
    """Exclusive lock on the run at ``path`` (a hidden lock file beside it, removed on release)."""
    if fcntl is None:
        yield
        return
    lock = path.with_name(f".{path.name}.lock")
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise DataError(f"{path}: cannot lock the run for writing ({exc.strerror or exc})") from None
        try:
            while True:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except BlockingIOError:
                    if time.monotonic() > deadline:
                        raise DataError(f"{path}: another process is saving into this run "
                                        f"(waited {timeout_s:g} s); try again") from None
                    time.sleep(0.05)
            mine = os.fstat(fd)
            try:
                cur = os.stat(lock)
            except FileNotFoundError:
                cur = None
        except BaseException:
            os.close(fd)
            raise
        if cur is not None and (cur.st_dev, cur.st_ino) == (mine.st_dev, mine.st_ino):
            break
        os.close(fd)  # the holder removed that lock file as it released it: lock the new one
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(lock)
        os.close(fd)


def _copy(src: Path, dst: Path) -> None:
    with open(src, "rb") as fi, open(dst, "xb") as fo:
        size = os.fstat(fi.fileno()).st_size
        done = 0
        fast = hasattr(os, "copy_file_range")
        while done < size:
            n = 0
            block = _FIRST_BLOCK if done == 0 else _COPY_BLOCK
            if fast:
                try:
                    n = os.copy_file_range(fi.fileno(), fo.fileno(), min(block, size - done), done, done)
                except OSError:
                    fast = False
            if not fast:
                fi.seek(done)
                fo.seek(done)
                chunk = fi.read(min(block, size - done))
                n = fo.write(chunk) if chunk else 0
            if n <= 0:
                raise DataError(f"{src}: changed size while being copied")
            done += n
            if done < size:
                stage("copying")
        fo.flush()
    shutil.copymode(src, dst)


def _fsync(path: Path, directory: bool = False) -> None:
    flags = os.O_RDONLY | (getattr(os, "O_DIRECTORY", 0) if directory else 0)
    try:
        fd = os.open(path, flags)
    except OSError:
        if directory:
            return  # some platforms cannot open a directory; the rename is still atomic
        raise
    try:
        os.fsync(fd)
    except OSError:
        if not directory:
            raise
    finally:
        os.close(fd)


def temp_name(path: Path) -> Path:
    return path.with_name(f".{path.name}.{os.getpid()}.edit.part")


def _remove_stale_temps(path: Path) -> None:
    for p in path.parent.glob(f".{path.name}.*.edit.part"):
        with contextlib.suppress(OSError):
            p.unlink()


@contextlib.contextmanager
def edit_copy(path: str | os.PathLike) -> Iterator[h5py.File]:
    """An ``r+`` h5py.File on a copy of the run; when the block ends without error the copy replaces the run."""
    path = Path(path)
    sb = check_file(path)
    if sb.open_for_write:
        raise RunStillOpen(
            f"{path}: the run is still open for writing (being recorded, or its writer was killed); "
            f"it can be read but not changed: `velab recover {path}` writes a closed copy")
    with open_h5(path) as fh:  # is it a velab run at all (never edit a foreign file)
        if L.to_str(fh.attrs.get("file_format", "")) != L.FILE_FORMAT or "entry" not in fh:
            raise DataError(f"{path}: not a velab run file (no /entry with file_format={L.FILE_FORMAT})")
        found = defects(fh)  # never write into a run that is not sound (velab.runfiles.soundness)
        if found:
            raise DataError(f"{path}: damaged run ({describe_defects(found)}): nothing is written into it")
    with run_lock(path):
        _remove_stale_temps(path)
        stage("locked")
        before = os.stat(path)
        free = shutil.disk_usage(path.parent).free
        if free < before.st_size + (16 << 20):
            raise DataError(f"{path}: not enough free disk space to save into the run "
                            f"(needs {before.st_size / 2**20 + 16:.0f} MiB, {free / 2**20:.0f} MiB free)")
        tmp = temp_name(path)
        try:
            _copy(path, tmp)
            stage("copied")
            try:
                fh = h5py.File(tmp, "r+", locking=False)
            except OSError as exc:
                raise DataError(f"{path}: cannot be opened for saving ({str(exc).splitlines()[0]})") from None
            with fh:
                yield fh
                stage("written")
            stage("closed")
            _fsync(tmp)
            stage("synced")
            after = os.stat(path)
            if (after.st_ino, after.st_size, after.st_mtime_ns) != (before.st_ino, before.st_size, before.st_mtime_ns):
                raise DataError(f"{path}: the run was changed by another program while saving; nothing saved")
            try:
                os.replace(tmp, path)
            except OSError as exc:
                raise DataError(f"{path}: cannot replace the run ({exc.strerror or exc}; "
                                "is it open in another program?); nothing saved") from None
            stage("replaced")
            trust(path)
            _fsync(path.parent, directory=True)
            stage("done")
        except BaseException:
            with contextlib.suppress(OSError):
                tmp.unlink()
            raise
