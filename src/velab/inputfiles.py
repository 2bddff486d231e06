"""Input files are checked before they are opened: a regular file, below a size cap.

A wrong path (a directory, a FIFO that would block, /dev/zero, a disk image) is a
one-line error, never an unbounded read. Leaf module (standard library + errors).
"""

from __future__ import annotations

import os
import stat

from velab.errors import DataError


def check_input_file(path, what: str = "file", max_bytes: int | None = None, error: type[Exception] = DataError):
    """Raise ``error`` unless ``path`` is an existing regular file of at most ``max_bytes``; returns its size."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise error(f"{path}: no such file") from None
    except ValueError:  # an embedded NUL byte
        raise error(f"{str(path)!r}: not a valid file name") from None
    except OSError as exc:
        raise error(f"{path}: cannot read: {exc.strerror or exc}") from None
    if stat.S_ISDIR(st.st_mode):
        raise error(f"{path}: is a directory, expected a {what}")
    if not stat.S_ISREG(st.st_mode):
        raise error(f"{path}: not a regular file, expected a {what}")
    if max_bytes is not None and st.st_size > max_bytes:
        raise error(f"{path}: {st.st_size} bytes, larger than the {_size(max_bytes)} accepted for a {what}")
    return st.st_size


def _size(n: int) -> str:
    for unit, k in (("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if n >= k:
            return f"{n / k:g} {unit}"
    return f"{n} bytes"
