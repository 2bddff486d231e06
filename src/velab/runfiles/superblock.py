"""The HDF5 superblock: where a file says it is "open for write", and its checksum.

HDF5 (superblock version 2 and 3, every file velab writes) keeps *status flags*
in the superblock: bit 0 "opened for write", bit 2 "opened for SWMR write".
A writer that dies without closing its file (SIGKILL, power loss) leaves them
set, and the HDF5 library then refuses an ordinary open. ``h5clear -s`` clears
them in place; velab never touches an original: it reads such a file with a
SWMR open (:mod:`velab.runfiles.reader`) and clears the flags only in a copy
(:func:`clear_status_flags`, used by ``velab recover``).

The superblock checksum is Bob Jenkins' lookup3 ``hashlittle`` (HDF5's
``H5_checksum_lookup3``); checking it ourselves lets a damaged superblock fail
at once instead of inside HDF5's SWMR retry loop.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass

SIGNATURE = b"\x89HDF\r\n\x1a\n"
WRITE_ACCESS = 0x01
SWMR_WRITE_ACCESS = 0x04
_M = 0xFFFFFFFF


def _rot(x: int, k: int) -> int:
    return ((x << k) | (x >> (32 - k))) & _M


def lookup3(data: bytes, initval: int = 0) -> int:
    """Jenkins' lookup3 hashlittle over ``data`` (HDF5's metadata checksum)."""
    n = len(data)
    a = b = c = (0xDEADBEEF + n + initval) & _M
    i = 0
    while n > 12:
        a = (a + int.from_bytes(data[i:i + 4], "little")) & _M
        b = (b + int.from_bytes(data[i + 4:i + 8], "little")) & _M
        c = (c + int.from_bytes(data[i + 8:i + 12], "little")) & _M
        a = (a - c) & _M; a ^= _rot(c, 4); c = (c + b) & _M  # noqa: E702 - the published mix, line by line
        b = (b - a) & _M; b ^= _rot(a, 6); a = (a + c) & _M  # noqa: E702
        c = (c - b) & _M; c ^= _rot(b, 8); b = (b + a) & _M  # noqa: E702
        a = (a - c) & _M; a ^= _rot(c, 16); c = (c + b) & _M  # noqa: E702
        b = (b - a) & _M; b ^= _rot(a, 19); a = (a + c) & _M  # noqa: E702
        c = (c - b) & _M; c ^= _rot(b, 4); b = (b + a) & _M  # noqa: E702
        n -= 12
        i += 12
    if n == 0:
        return c
    tail = bytes(data[i:i + n]) + bytes(12 - n)
    a = (a + int.from_bytes(tail[0:4], "little")) & _M
    b = (b + int.from_bytes(tail[4:8], "little")) & _M
    c = (c + int.from_bytes(tail[8:12], "little")) & _M
    c ^= b; c = (c - _rot(b, 14)) & _M  # noqa: E702 - the published final mix
    a ^= c; a = (a - _rot(c, 11)) & _M  # noqa: E702
    b ^= a; b = (b - _rot(a, 25)) & _M  # noqa: E702
    c ^= b; c = (c - _rot(b, 16)) & _M  # noqa: E702
    a ^= c; a = (a - _rot(c, 4)) & _M  # noqa: E702
    b ^= a; b = (b - _rot(a, 14)) & _M  # noqa: E702
    c ^= b; c = (c - _rot(b, 24)) & _M  # noqa: E702
    return c


class SuperblockError(ValueError):
    """The file has no readable HDF5 superblock (not HDF5, or damaged)."""


@dataclass(frozen=True)
class Superblock:
    offset: int  # where the signature is (0 unless there is a user block)
    version: int
    flags: int  # status flags (versions 2, 3); 0 for older versions
    size_of_offsets: int
    eoa: int | None  # end-of-file address as the superblock records it (versions 2, 3)
    checksum_ok: bool  # True for versions without a checksum

    @property
    def open_for_write(self) -> bool:
        return bool(self.flags & WRITE_ACCESS)

    @property
    def swmr_write(self) -> bool:
        return bool(self.flags & SWMR_WRITE_ACCESS)

    @property
    def length(self) -> int:
        """Bytes of a version 2/3 superblock, checksum included."""
        return 16 + 4 * self.size_of_offsets


def _find_signature(fh, size: int) -> int:
    off = 0
    while off + len(SIGNATURE) <= size:
        fh.seek(off)
        if fh.read(len(SIGNATURE)) == SIGNATURE:
            return off
        off = 512 if off == 0 else off * 2  # a user block is a power of two >= 512
    raise SuperblockError("no HDF5 signature (not an HDF5 file)")


def read_superblock(path: str | os.PathLike) -> Superblock:
    with open(path, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        off = _find_signature(fh, size)
        fh.seek(off)
        head = fh.read(64)
    if len(head) < 12:
        raise SuperblockError("truncated superblock")
    version = head[8]
    if version < 2:
        return Superblock(off, version, 0, 8, None, True)
    if version > 3:
        raise SuperblockError(f"unknown superblock version {version}")
    so = head[9]
    if so not in (2, 4, 8):
        raise SuperblockError(f"superblock: impossible size of offsets {so}")
    n = 12 + 4 * so
    if len(head) < n + 4:
        raise SuperblockError("truncated superblock")
    stored = struct.unpack("<I", head[n:n + 4])[0]
    eoa = int.from_bytes(head[12 + 2 * so:12 + 3 * so], "little")
    return Superblock(off, version, head[11], so, eoa, lookup3(head[:n]) == stored)


def clear_status_flags(path: str | os.PathLike) -> bool:
    """Reset the status flags of the file at ``path`` and re-checksum its superblock.

    What ``h5clear -s`` does, for the *copy* velab recover makes (never an
    original). Returns False when there was nothing to clear.
    """
    sb = read_superblock(path)
    if sb.version < 2 or not sb.flags:
        return False
    if not sb.checksum_ok:
        raise SuperblockError("superblock checksum mismatch (damaged file)")
    with open(path, "r+b") as fh:
        fh.seek(sb.offset)
        head = bytearray(fh.read(sb.length))
        head[11] = 0
        n = sb.length - 4
        head[n:] = struct.pack("<I", lookup3(bytes(head[:n])))
        fh.seek(sb.offset)
        fh.write(head)
        fh.flush()
        os.fsync(fh.fileno())
    return True
