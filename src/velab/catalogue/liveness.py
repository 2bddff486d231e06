"""Is a run whose file says ``recording`` still being recorded, or was its recorder killed?

A run file says ``recording`` from its creation until the writer closes it, and a
writer that dies (SIGKILL, a crash, power loss) leaves it so, with the superblock's
"open for write" flag set (docs/run-format.md). The file itself cannot tell the two
apart and the recorder holds no lock on it (HDF5 releases its own file lock in SWMR
mode), so the listing looks, each time (a row in the index was read when the file
last changed, and a killed run's file never changes again):

- a local process has the file open for writing (Linux ``/proc/PID/fd``, the writer
  opens it read-write, SWMR readers read-only): ``recording``;
- else, when every process could be looked at and the file is on a local file
  system: ``interrupted`` at once;
- else (another user's processes, a network file system where the writer may be on
  another machine): ``interrupted`` once the file has not changed for
  :data:`QUIET_S` (a live recorder flushes at least every 0.5 s).

Standard library only, and nothing to do when no row says ``recording``.
"""

from __future__ import annotations

import datetime as _dt
import os
import time

QUIET_S = 120.0  # no write for this long and no writer seen: interrupted (network file systems cache mtimes ~60 s)
_NETWORK_FS = ("nfs", "nfs4", "cifs", "smb3", "smbfs", "9p", "ceph", "glusterfs", "lustre", "gpfs", "afs",
               "fuse.sshfs", "fuse.glusterfs", "fuse.s3fs", "davfs", "fuse.rclone")


def writers(paths: list[str]) -> tuple[set[str], bool]:
    """(the paths some local process has open for writing, whether every process could be looked at)."""
    want: dict[tuple[int, int], str] = {}
    for p in paths:
        try:
            st = os.stat(p)
        except OSError:
            continue
        want[(st.st_dev, st.st_ino)] = p
    names = {os.path.basename(p) for p in want.values()}
    held: set[str] = set()
    try:
        pids = [d for d in os.listdir("/proc") if d.isdigit()]
    except OSError:  # not Linux: nothing can be told
        return held, False
    complete = True
    for pid in pids:
        try:
            fds = os.listdir(f"/proc/{pid}/fd")
        except FileNotFoundError:
            continue  # ended meanwhile
        except OSError:
            complete = False  # another user's process: it may be the writer
            continue
        for fd in fds:
            link = f"/proc/{pid}/fd/{fd}"
            try:
                if os.path.basename(os.readlink(link)) not in names:
                    continue  # cheap test first: a stat for the few fds that may be ours
                st = os.stat(link)
                p = want.get((st.st_dev, st.st_ino))
                if p is None:
                    continue
                with open(f"/proc/{pid}/fdinfo/{fd}") as fh:
                    flags = next(int(ln.split()[1], 8) for ln in fh if ln.startswith("flags:"))
            except (OSError, StopIteration, ValueError):
                continue
            if flags & os.O_ACCMODE != os.O_RDONLY:
                held.add(p)
    return held, complete


def _mounts() -> list[tuple[str, str]]:
    """(mount point, file system type), longest mount point first."""
    out = []
    try:
        with open("/proc/self/mountinfo") as fh:
            for ln in fh:
                left, _, right = ln.partition(" - ")
                point = left.split()[4].replace("\\040", " ")
                out.append((point, right.split()[0]))
    except (OSError, IndexError):
        return []
    return sorted(out, key=lambda m: len(m[0]), reverse=True)


def is_local(path: str, mounts: list[tuple[str, str]]) -> bool:
    real = os.path.realpath(path)
    for point, fstype in mounts:
        if real == point or real.startswith(point.rstrip("/") + "/"):
            return fstype not in _NETWORK_FS
    return False  # unknown: wait for the quiet time


def settle(rows: list[dict], now: float | None = None) -> list[str]:
    """Rows saying ``recording`` whose writer is gone become ``interrupted`` with a one-line reason (in place);
    the paths of the rows changed."""
    rec = [r for r in rows if r.get("status") == "recording"]
    changed: list[str] = []
    if not rec:
        return changed
    held, complete = writers([r["path"] for r in rec])
    mounts = _mounts() if complete else []
    now = time.time() if now is None else now
    for r in rec:
        if r["path"] in held:
            continue
        mtime = r.get("mtime")
        quiet = isinstance(mtime, (int, float)) and now - mtime > QUIET_S
        if not (quiet or complete and is_local(r["path"], mounts)):
            continue  # a writer elsewhere may still be flushing into it: not yet known
        when = _dt.datetime.fromtimestamp(mtime).astimezone().isoformat(timespec="seconds") \
            if isinstance(mtime, (int, float)) else "an unknown time"
        own = r.get("reason") or ""
        if r.get("open_for_write"):
            why = f"recording stopped at {when}, no writer holds it; `velab recover` can close it"
            r["reason"] = f"{own} ({why})" if own else why
        else:  # closed but never concluded (a recovered copy says so itself)
            r["reason"] = own or f"recording stopped at {when} and never concluded"
        r["status"] = "interrupted"
        changed.append(r["path"])
    return changed
