"""Opening an HDF5 file for reading without ever hanging, whatever state it is in.

* A closed file opens normally (read-only, no file lock: velab never writes in place).
* A file a SWMR writer holds open, or left flagged by a killed SWMR writer, opens
  as a SWMR reader with a bounded number of metadata read attempts: HDF5's
  default is 100 attempts with a doubling sleep between them, which on a
  damaged file is a hang of hours.
* A file left flagged by a non-SWMR writer (an old in-place fit save that was
  killed) is read through a view whose superblock has the flags cleared, as
  ``h5clear -s`` would do, without touching the file.
* The superblock checksum is checked first, so a damaged superblock fails at once.
* The structure is walked in a child process under a deadline before this process
  reads it (:mod:`velab.runfiles.probe`): damage that makes HDF5 itself loop fails too.

Every failure is a :class:`~velab.errors.DataError` (or :class:`RunStillOpen`) of one line.
"""

from __future__ import annotations

import contextlib
import ctypes
import glob
import io
import os
import struct
from pathlib import Path
from typing import Iterator

import h5py
from h5py import h5f, h5p

from velab.errors import DataError
from velab.runfiles import superblock as sb_
from velab.runfiles.probe import ensure_walkable

# 2^N ns is the longest sleep of the last attempt; 24 attempts give up within ~35 ms,
# ample for a reader that raced a live writer's flush.
SWMR_READ_ATTEMPTS = 24


class RunStillOpen(DataError):
    """The file is held open by a writer, or its writer died without closing it."""


def _libhdf5():
    """The HDF5 library h5py runs on (for the one call h5py does not wrap)."""
    candidates = []
    if os.path.exists("/proc/self/maps"):
        with open("/proc/self/maps") as fh:
            candidates = sorted({ln.split()[-1] for ln in fh if "libhdf5" in ln and "_hl" not in ln
                                 and ln.split()[-1].startswith("/")})
    if not candidates:  # macOS, Windows: the copy bundled with the h5py wheel
        base = Path(h5py.__file__).parent
        for pattern in ("../h5py.libs/libhdf5*", "../h5py/.dylibs/libhdf5*", "*hdf5*.dll", ".dylibs/libhdf5*"):
            candidates += [p for p in glob.glob(str(base / pattern)) if "_hl" not in p]
    for path in candidates:
        try:
            lib = ctypes.CDLL(path)
            fn = lib.H5Pset_metadata_read_attempts
        except (OSError, AttributeError):
            continue
        fn.argtypes = [ctypes.c_int64, ctypes.c_uint]
        fn.restype = ctypes.c_int
        return fn
    return None


_set_attempts = _libhdf5()


def _swmr_reader(path: Path) -> h5py.File:
    if _set_attempts is None:
        return h5py.File(_ClearedFlags(path), "r")
    fapl = h5p.create(h5p.FILE_ACCESS)
    fapl.set_libver_bounds(h5f.LIBVER_EARLIEST, h5f.LIBVER_LATEST)
    fapl.set_file_locking(False, True)
    if _set_attempts(fapl.id, SWMR_READ_ATTEMPTS) < 0:
        return h5py.File(_ClearedFlags(path), "r")
    fid = h5f.open(os.fsencode(path), h5f.ACC_RDONLY | h5f.ACC_SWMR_READ, fapl=fapl)
    return h5py.File(fid)


class _ClearedFlags(io.RawIOBase):
    """The file's bytes, read-only, with the superblock's status flags cleared (in memory only)."""

    def __init__(self, path: Path):
        super().__init__()
        sb = sb_.read_superblock(path)
        self._f = open(path, "rb")
        self._f.seek(sb.offset)
        head = bytearray(self._f.read(sb.length))
        head[11] = 0
        n = sb.length - 4
        head[n:] = struct.pack("<I", sb_.lookup3(bytes(head[:n])))
        self._sb, self._sb_at = bytes(head), sb.offset
        self._pos = 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def seek(self, offset: int, whence: int = 0) -> int:
        size = os.fstat(self._f.fileno()).st_size
        self._pos = offset if whence == 0 else self._pos + offset if whence == 1 else size + offset
        return self._pos

    def tell(self) -> int:
        return self._pos

    def readinto(self, b) -> int:
        self._f.seek(self._pos)
        k = self._f.readinto(b)
        lo, hi = max(self._pos, self._sb_at), min(self._pos + k, self._sb_at + len(self._sb))
        if lo < hi:
            b[lo - self._pos:hi - self._pos] = self._sb[lo - self._sb_at:hi - self._sb_at]
        self._pos += k
        return k

    def close(self) -> None:
        self._f.close()
        super().close()


def _one_line(exc: BaseException) -> str:
    msg = str(exc).split("\n")[0].strip()
    return msg or type(exc).__name__


def check_file(path: str | os.PathLike) -> sb_.Superblock:
    """The checks before HDF5 sees the file: exists, regular, HDF5 signature, sound superblock."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such file")
    if path.is_dir():
        raise DataError(f"{path}: is a directory, expected a run file (.h5)")
    if not path.is_file():
        raise DataError(f"{path}: not a regular file")
    try:
        sb = sb_.read_superblock(path)
    except sb_.SuperblockError as exc:
        what = str(exc)
        raise DataError(f"{path}: {'not an HDF5 file' if 'signature' in what else 'damaged HDF5 file: ' + what}") from None
    except OSError as exc:
        raise DataError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    if not sb.checksum_ok:
        raise DataError(f"{path}: damaged HDF5 file: superblock checksum mismatch")
    return sb


@contextlib.contextmanager
def open_h5(path: str | os.PathLike, *, probe: bool = True) -> Iterator[h5py.File]:
    """Open ``path`` read-only (see the module docstring); every failure one DataError line.

    ``probe``: walk the file's structure in a child process first (:mod:`velab.runfiles.probe`).
    """
    path = Path(path)
    sb = check_file(path)
    if probe:
        ensure_walkable(path)
    try:
        if not sb.open_for_write:
            fh = h5py.File(path, "r", locking=False)
        elif sb.swmr_write:
            fh = _swmr_reader(path)
        else:
            fh = h5py.File(_ClearedFlags(path), "r")
    except (OSError, ValueError, RuntimeError, KeyError) as exc:
        msg = _one_line(exc)
        if sb.open_for_write:
            raise RunStillOpen(f"{path}: cannot be read: it is flagged open for writing and damaged ({msg}); "
                               f"`velab recover {path}` may save what is left") from None
        raise DataError(f"{path}: cannot be opened as HDF5, truncated or corrupt ({msg})") from None
    try:
        yield fh
    finally:
        try:
            fh.close()
        except Exception:  # noqa: BLE001 - closing a damaged file must not mask the real error
            pass


def walk(path: str) -> int:
    """Child side: open like the parent would, touch every object, attribute and chunk index."""
    def visit(name, obj):
        for k in obj.attrs:
            obj.attrs.get(k)
        if isinstance(obj, h5py.Dataset):
            if obj.chunks is not None:
                obj.id.get_num_chunks()
            if obj.size <= 64 or h5py.check_string_dtype(obj.dtype) is not None and obj.size <= 4096:
                obj[()]

    try:
        with open_h5(path, probe=False) as fh:
            for k in fh.attrs:
                fh.attrs.get(k)
            fh.visititems(visit)
    except DataError as exc:
        print(str(exc))
        return 3
    except Exception as exc:  # noqa: BLE001 - anything the library raises on a damaged file
        msg = str(exc).split("\n")[0].strip()
        print(f"{path}: damaged HDF5 file ({type(exc).__name__}{': ' + msg if msg else ''})")
        return 3
    return 0
