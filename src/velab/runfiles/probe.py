"""Walk a file's HDF5 structure in a child process first, under a deadline.

Some damage makes the HDF5 library itself loop forever (found by the fuzz: a
zeroed range in an object header makes an attribute read never return), or
crash; h5py holds the GIL inside the library, so no thread or signal of ours can
stop it. Before velab reads a file in its own process it walks every group,
attribute and chunk index once in a child process (``python -c``, h5py only,
~0.3 s): a child that does not finish in :data:`PROBE_TIMEOUT_S` or dies is a
one-line DataError, and the file is never touched by the parent's HDF5.

Files this process wrote or saved itself, and files already walked, are not
walked again while their (device, inode, size, mtime) stay the same.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path

from velab.errors import DataError

PROBE_TIMEOUT_S = 10.0
_known: set[tuple] = set()
_lock = threading.Lock()

_CHILD = """
import sys
from velab.runfiles.h5open import walk
sys.exit(walk(sys.argv[1]))
"""


def _key(path: Path) -> tuple | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)


def trust(path: str | os.PathLike) -> None:
    """``path`` was just written or saved by this process: no need to walk it."""
    key = _key(Path(path))
    if key is not None:
        with _lock:
            _known.add(key)


def ensure_walkable(path: Path) -> None:
    key = _key(path)
    with _lock:
        if key is not None and key in _known:
            return
    if os.environ.get("VELAB_PROBE_CHILD"):  # we are the child: no grandchildren
        return
    env = dict(os.environ, VELAB_PROBE_CHILD="1")
    try:
        out = subprocess.run([sys.executable, "-c", _CHILD, str(path)], capture_output=True, text=True,
                             timeout=PROBE_TIMEOUT_S, env=env)
    except subprocess.TimeoutExpired:
        raise DataError(f"{path}: damaged HDF5 file: reading its structure does not finish "
                        f"(gave up after {PROBE_TIMEOUT_S:g} s)") from None
    except OSError as exc:  # cannot start a child: read in-process (no deadline)
        del exc
        return
    if out.returncode == 0:
        with _lock:
            if key is not None and key == _key(path):
                _known.add(key)
        return
    line = (out.stdout.strip().splitlines() or [""])[-1]
    if out.returncode == 3 and line:
        raise DataError(line)
    raise DataError(f"{path}: damaged HDF5 file: the HDF5 library failed reading it (exit {out.returncode})")
