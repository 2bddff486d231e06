"""The catalogue's index: an SQLite file of one row per run file, kept up to date by (path, size, mtime).

Where (:func:`default_path`): ``$VELAB_CATALOGUE`` if set; else
``$XDG_CACHE_HOME/velab/catalogue.sqlite`` (``~/.cache/velab``); where that cannot
be written, ``.velab-catalogue.sqlite`` beside the archive (the first folder listed);
else an in-memory index (correct, only not kept).

:meth:`Catalogue.update` walks the folders (hidden names skipped: the temporary
``.NAME.h5.part`` and lock files of writers), keeps the row of every file whose
(size, mtime, inode) did not change, reads the others in worker processes
(:mod:`velab.catalogue.extract`) and forgets files that are gone. A file is keyed
by its state *before* it is read, so a run being recorded, which grows between
two listings, is read again by the next one.

Safe with several readers and a recorder at once: WAL journal (readers never wait
for a writer), a busy timeout, each batch of rows one ``BEGIN IMMEDIATE``
transaction. A damaged or foreign index file is deleted and rebuilt without a word
(it holds nothing that is not in the run files), under a lock file and only when it
is still damaged under that lock; "locked" or "busy" is never taken for damage (a
fresh index being set up by another process is waited for). Run files are only ever read.

Each row is kept as its JSON text plus the :data:`LIGHT` columns (what filters and
sort keys read): ``update(light=True)`` answers 10,000 rows without decoding them,
and ``velab runs --json`` copies the texts (:attr:`Listing.texts`) into its document.
Whether a ``recording`` row is live or interrupted is decided at each listing
(:mod:`velab.catalogue.liveness`), never stored.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import sqlite3
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable

from velab.catalogue import RUN_SUFFIXES

log = logging.getLogger("velab.catalogue")

SCHEMA = 2  # 2: the light columns
# the fields filters and sort keys use, kept as columns beside the row's JSON: a listing filters and sorts
# on them without decoding 10,000 JSON rows (velab.catalogue.query.FILTER_FIELDS and SORT_KEYS)
LIGHT = ("kind", "status", "start_time", "mtime", "title", "operator", "specimen", "notes", "rig", "best_model",
         "steady_flow_l_s", "measured_flow_l_s", "beta_per_s", "sample_rate_hz", "duration_s", "wave_speed_m_s",
         "wave_speed_se_m_s", "n_fits", "noise_ratio")
_KEY = slice(len(LIGHT) + 1, len(LIGHT) + 4)  # (size, mtime_ns, ino) in a stored() tuple
_COLUMNS = ("path", "size", "mtime_ns", "ino", "row", "indexed") + tuple("l_" + k for k in LIGHT)
FILE_NAME = "catalogue.sqlite"
BESIDE_NAME = ".velab-catalogue.sqlite"
BUSY_TIMEOUT_MS = 30_000
BATCH_ROWS = 200  # rows per transaction while indexing (a killed indexer keeps what it committed)
BATCH_S = 1.0


def _version() -> int:
    from velab.catalogue.rows import ROW_VERSION

    return SCHEMA * 1000 + ROW_VERSION


def _writable_dir(d: Path) -> bool:
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError:
        return False
    return os.access(d, os.W_OK | os.X_OK)


def default_path(roots: Iterable[str | os.PathLike] = ()) -> str:
    """Where the index lives (module docstring); ``":memory:"`` when nowhere can be written."""
    env = os.environ.get("VELAB_CATALOGUE")
    if env:
        return env
    cache = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    d = Path(cache) / "velab"
    if _writable_dir(d):
        return str(d / FILE_NAME)
    for r in roots:
        r = Path(r)
        r = r if r.is_dir() else r.parent
        if os.access(r, os.W_OK | os.X_OK):
            return str(r / BESIDE_NAME)
    return ":memory:"


@dataclass
class Listing:
    """What one update found under the folders."""

    rows: list[dict]  # runs and damaged files, path order
    others: list[dict] = field(default_factory=list)  # HDF5 files that are not runs
    files: int = 0  # candidate files seen
    read: int = 0  # files (re)read this time
    removed: int = 0
    seconds: float = 0.0
    index_path: str = ""
    texts: dict[str, str] = field(default_factory=dict)  # path -> the row as strict JSON, where it is as stored

    def full(self, row: dict) -> dict:
        """The whole row of a light one (``update(light=True)``); a whole row as it is."""
        if "elements" in row or row["path"] not in self.texts:  # every whole row has "elements"
            return row
        try:
            return json.loads(self.texts[row["path"]])
        except ValueError:  # cannot happen to a text rows.dumps wrote; the light row rather than nothing
            return row


def scan(roots: Iterable[str | os.PathLike]) -> dict[str, tuple[int, int, int]]:
    """Absolute path -> (size, mtime_ns, inode) of every candidate run file under the roots."""
    out: dict[str, tuple[int, int, int]] = {}

    def add(path: str, st: os.stat_result) -> None:
        out[path] = (st.st_size, st.st_mtime_ns, st.st_ino)

    def walk(d: str) -> None:
        try:
            it = os.scandir(d)
        except OSError as exc:  # an unreadable sub-folder: say so, list the rest
            log.warning("%s: cannot be listed (%s)", d, exc.strerror or exc)
            return
        with it:
            for entry in it:
                if entry.name.startswith("."):
                    continue
                try:
                    if entry.is_dir(follow_symlinks=False):
                        walk(entry.path)
                    elif entry.name.lower().endswith(RUN_SUFFIXES) and entry.is_file():
                        add(entry.path, entry.stat())
                except OSError:
                    continue  # vanished meanwhile (a writer's rename)

    for r in roots:
        r = os.path.abspath(os.fspath(r))
        if os.path.isdir(r):
            walk(r)
        elif os.path.isfile(r):
            add(r, os.stat(r))
    return out


def _prefix_range(root: str) -> tuple[str, str]:
    """Paths under the folder ``root`` are those in [root + "/", root + "0") ("0" follows "/")."""
    root = root.rstrip(os.sep)
    return root + os.sep, root + chr(ord(os.sep) + 1)


class Catalogue:
    """The index file, opened (and created or rebuilt) on construction. One per thread."""

    def __init__(self, path: str | os.PathLike | None = None, roots: Iterable[str | os.PathLike] = ()):
        self.path = str(path) if path is not None else default_path(roots)
        self.db = self._open()

    # ------------------------------------------------------------------ the file
    def _connect(self) -> sqlite3.Connection:
        db = sqlite3.connect(self.path, timeout=BUSY_TIMEOUT_MS / 1000, isolation_level=None,
                             check_same_thread=False)
        try:
            db.execute(f"PRAGMA busy_timeout={BUSY_TIMEOUT_MS}")
            if self.path != ":memory:":
                # changing the journal mode can answer "locked" without waiting while another
                # process creates the same fresh file: retried, never taken for damage
                _retry(lambda: db.execute("PRAGMA journal_mode=WAL"))
                db.execute("PRAGMA synchronous=NORMAL")  # WAL + NORMAL: a crash loses at most the last batch
            if not _retry(lambda: _ready(db)):
                _retry(lambda: self._create(db))
            db.execute("SELECT count(*) FROM files").fetchone()
        except BaseException:
            db.close()
            raise
        if self.path != ":memory:":
            st = os.stat(self.path)
            self._file_id = (st.st_dev, st.st_ino)
        return db

    @staticmethod
    def _create(db: sqlite3.Connection) -> None:
        """The table, made (or remade for another version) in one transaction, the version re-read under its lock:
        a process that created it meanwhile is not undone."""
        db.execute("BEGIN IMMEDIATE")
        try:
            if not _ready(db):
                db.execute("DROP TABLE IF EXISTS files")
                db.execute("CREATE TABLE IF NOT EXISTS files (path TEXT PRIMARY KEY, size INTEGER, "
                           "mtime_ns INTEGER, ino INTEGER, row TEXT, indexed REAL, "
                           + ", ".join(f"l_{k}" for k in LIGHT) + ")")
                db.execute(f"PRAGMA user_version={_version()}")
            db.execute("COMMIT")
        except BaseException:
            if db.in_transaction:
                db.execute("ROLLBACK")
            raise

    def _open(self) -> sqlite3.Connection:
        try:
            return _retry(self._connect)
        except sqlite3.DatabaseError as exc:
            if not _damaged(exc):  # still locked after the retries, or cannot be written: not kept this time
                return self._in_memory(exc)
            try:
                return self._rebuild()
            except sqlite3.DatabaseError as exc2:  # cannot be written there either: in memory
                return self._in_memory(exc2)

    def _in_memory(self, exc: Exception) -> sqlite3.Connection:
        log.warning("catalogue %s cannot be used (%s): not kept this time", self.path, exc)
        self.path = ":memory:"
        return self._connect()

    def _rebuild(self) -> sqlite3.Connection:
        """A damaged or foreign index deleted and made again, under a lock file.

        Damage is judged again under the lock: another process may have rebuilt it
        meanwhile, and deleting that fresh index would pull it from under its users.
        """
        if self.path == ":memory:":
            return self._connect()
        with _lock(self.path + ".lock"):
            try:
                return self._connect()
            except sqlite3.DatabaseError as exc:
                if not _damaged(exc):
                    raise
                log.debug("catalogue %s unusable (%s): rebuilt", self.path, exc)
            self._remove()
            return _retry(self._connect)

    def _remove(self) -> None:
        if self.path == ":memory:":
            return
        for suffix in ("", "-wal", "-shm", "-journal"):
            try:
                os.unlink(self.path + suffix)
            except FileNotFoundError:
                pass

    def close(self) -> None:
        self.db.close()

    def __enter__(self) -> "Catalogue":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ reading
    def stored(self, roots: Iterable[str | os.PathLike]) -> dict[str, tuple]:
        """path -> (path, *the LIGHT fields, size, mtime_ns, ino, row JSON) of what the index holds under the roots.

        In this order so that ``dict(zip(("path",) + LIGHT, t))`` is the light row and ``t[_KEY]`` the file's key.
        """
        out = {}
        light = ", ".join(f"l_{k}" for k in LIGHT)
        for r in roots:
            r = os.path.abspath(os.fspath(r))
            q = f"SELECT path, {light}, size, mtime_ns, ino, row FROM files WHERE "
            if os.path.isdir(r):
                rows = self._query(q + "path >= ? AND path < ?", _prefix_range(r))
            else:
                rows = self._query(q + "path = ?", (r,))
            out.update({t[0]: t for t in rows})
        return out

    def _query(self, sql: str, params=()) -> list:
        """Rows of a read; the table gone or the file damaged under us (another process rebuilt it): opened
        again, read again once (an empty index then, the rows come back from the files)."""
        try:
            return self.db.execute(sql, params).fetchall()
        except sqlite3.DatabaseError as exc:
            if not (_damaged(exc) or "no such table" in str(exc)):
                raise
            log.debug("catalogue %s unusable while reading (%s): opened again", self.path, exc)
            self.db.close()
            self.db = self._rebuild() if _damaged(exc) else self._open()
            return self.db.execute(sql, params).fetchall()

    def cached(self, roots: Iterable[str | os.PathLike]) -> Listing:
        """What the index holds under the roots, without looking at the files (the GUI's first paint)."""
        texts = {p: v[-1] for p, v in self.stored(list(roots)).items()}
        return _listing(_decode(texts), 0, 0, 0, self.path, texts=texts)

    # ------------------------------------------------------------------ updating
    def update(self, roots: Iterable[str | os.PathLike], *, jobs: int | None = None, rebuild: bool = False,
               progress: Callable[[int, int], None] | None = None,
               on_rows: Callable[[list[dict]], None] | None = None,
               stop: Callable[[], bool] | None = None, fork: bool | None = None,
               deadline_s: float | None = None, light: bool = False) -> Listing:
        """Bring the index up to date for ``roots`` and return their rows (module docstring).

        ``progress(done, total)`` after each batch of files read; ``on_rows(rows)`` with each
        batch of rows read (the GUI adds them as they come); ``stop()`` true: end early.
        ``light``: the rows from the index carry only ``path`` and the :data:`LIGHT` fields
        (enough to filter and sort); :meth:`Listing.full` decodes the ones kept.
        """
        from velab.catalogue.extract import DEADLINE_S, read_rows

        t0 = time.perf_counter()
        roots = [os.path.abspath(os.fspath(r)) for r in roots]
        for r in roots:
            if not os.path.exists(r):
                from velab.errors import DataError

                raise DataError(f"{r}: no such folder")
        seen = scan(roots)
        keys = {} if rebuild else self._keys(roots)
        stale = sorted(p for p, k in seen.items() if keys.get(p) != k)
        reader = None
        if stale:
            jobs = jobs or min(2, os.cpu_count() or 1)
            if len(stale) < 4:  # a child per core costs an import each: not worth it for a few files
                jobs = 1
            reader = read_rows(stale, jobs=jobs, fork=fork, stop=stop, deadline_s=deadline_s or DEADLINE_S,
                               prime=True)
            next(reader)  # the children start (import, read) while the index is read below
        try:
            stale_set = set(stale)
            stored = self.stored(roots)
            texts = {p: v[-1] for p, v in stored.items() if p not in stale_set and v[_KEY] == seen.get(p)}
            if light:  # a recording is decoded whole: its liveness needs more than the light fields
                rows = {p: dict(zip(_LIGHT_KEYS, stored[p])) for p in texts}
                rows.update(_decode({p: texts[p] for p, r in rows.items() if r["status"] == "recording"}))
            else:
                rows = _decode(texts)
            gone = [p for p in stored if p not in seen]
            if gone:
                self._write(lambda db: db.executemany("DELETE FROM files WHERE path = ?", [(p,) for p in gone]))
            if reader is not None:
                self._read(reader, rows, texts, seen, len(stale), progress, on_rows)
        finally:
            if reader is not None:
                reader.close()
        return _listing(rows, len(seen), len(stale), len(gone), self.path, time.perf_counter() - t0, texts)

    def _read(self, reader, rows: dict, texts: dict, seen: dict, total: int, progress, on_rows) -> None:
        """The rows the workers read, stored a batch at a time (a killed listing keeps what it committed)."""
        batch, last = [], time.monotonic()
        done = 0
        for row in reader:
            rows[row["path"]] = row
            texts.pop(row["path"], None)
            batch.append(row)
            done += 1
            if len(batch) >= BATCH_ROWS or time.monotonic() - last > BATCH_S:
                texts.update(self._store(batch, seen))
                if on_rows:
                    on_rows(_settled(batch))
                if progress:
                    progress(done, total)
                batch, last = [], time.monotonic()
        if batch:
            texts.update(self._store(batch, seen))
            if on_rows:
                on_rows(_settled(batch))
        if progress:
            progress(done, total)

    def _keys(self, roots: list[str]) -> dict[str, tuple[int, int, int]]:
        """path -> (size, mtime_ns, ino) the index holds under the roots (what tells a file changed)."""
        out = {}
        for r in roots:
            q = "SELECT path, size, mtime_ns, ino FROM files WHERE "
            rows = self._query(q + "path >= ? AND path < ?", _prefix_range(r)) if os.path.isdir(r) else \
                self._query(q + "path = ?", (r,))
            out.update({t[0]: t[1:] for t in rows})
        return out

    def _store(self, rows: list[dict], keys: dict[str, tuple[int, int, int]]) -> dict[str, str]:
        """Store the rows; their JSON texts by path."""
        from velab.catalogue.rows import dumps

        now = time.time()
        values = [(r["path"], *keys[r["path"]], dumps(r), now, *(r.get(k) for k in LIGHT))
                  for r in rows if r["path"] in keys]
        sql = f"INSERT OR REPLACE INTO files ({', '.join(_COLUMNS)}) VALUES ({', '.join('?' * len(_COLUMNS))})"
        self._write(lambda db: db.executemany(sql, values))
        return {v[0]: v[4] for v in values}

    def _replaced(self) -> bool:
        """The index file under our path is no longer the one our connection has open."""
        if self.path == ":memory:":
            return False
        try:
            st = os.stat(self.path)
        except FileNotFoundError:
            return True
        return (st.st_dev, st.st_ino) != self._file_id

    def _write(self, fn) -> None:
        """One write transaction. Busy past the timeout: this batch is not kept. The table gone (another
        process rebuilt a damaged index under us) or the file damaged: opened again and the batch retried once."""
        if self._replaced():  # rebuilt by another process (it was damaged): ours is a deleted file now
            self.db.close()
            self.db = self._open()
        for attempt in (0, 1):
            try:
                self.db.execute("BEGIN IMMEDIATE")
                try:
                    fn(self.db)
                    self.db.execute("COMMIT")
                except BaseException:
                    if self.db.in_transaction:
                        self.db.execute("ROLLBACK")
                    raise
                return
            except sqlite3.DatabaseError as exc:
                if _busy(exc):
                    log.warning("catalogue %s busy: this listing's rows are not kept (%s)", self.path, exc)
                    return
                if attempt or not (_damaged(exc) or "no such table" in str(exc)):
                    raise
                log.debug("catalogue %s unusable while writing (%s): opened again", self.path, exc)
                self.db.close()
                self.db = self._rebuild() if _damaged(exc) else self._open()


def _settled(rows: list[dict]) -> list[dict]:
    """Copies of the rows with live and abandoned recordings told apart (the stored rows stay as read)."""
    from velab.catalogue.liveness import settle

    out = [dict(r) if r.get("status") == "recording" else r for r in rows]
    settle(out)
    return out


def _ready(db: sqlite3.Connection) -> bool:
    """The index is of this version and has its table (a version number alone survives a dropped table)."""
    return db.execute("PRAGMA user_version").fetchone()[0] == _version() and \
        db.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'files'").fetchone() is not None


def _busy(exc: BaseException) -> bool:
    return getattr(exc, "sqlite_errorname", "") in ("SQLITE_BUSY", "SQLITE_LOCKED") or \
        any(w in str(exc) for w in ("database is locked", "database table is locked", "busy"))


def _damaged(exc: BaseException) -> bool:
    """A file that is not (or no longer) an SQLite database: the only reason to delete an index."""
    return getattr(exc, "sqlite_errorname", "") in ("SQLITE_NOTADB", "SQLITE_CORRUPT") or \
        any(w in str(exc) for w in ("file is not a database", "malformed"))


def _retry(fn, tries: int = 8):
    """fn() again after a short, growing pause while SQLite answers busy or locked (a fresh file being set up,
    where SQLite may answer at once, without its busy timeout); not past the busy timeout (5 s at least) in all."""
    end = time.monotonic() + max(BUSY_TIMEOUT_MS / 1000, 5.0)
    for i in range(tries):
        try:
            return fn()
        except sqlite3.DatabaseError as exc:
            if not _busy(exc) or i == tries - 1 or time.monotonic() > end:
                raise
            time.sleep(0.02 * 2 ** i)


@contextlib.contextmanager
def _lock(path: str):
    """An exclusive lock file (fcntl) around the rebuild; none where fcntl is missing."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


_LIGHT_KEYS = ("path",) + LIGHT
def _decode(texts: dict[str, str]) -> dict[str, dict]:
    """path -> row of the stored JSON texts; a text that is not a row is dropped (from ``texts`` too: read again)."""
    out = {}
    loads = json.loads
    for p, text in list(texts.items()):
        try:
            row = loads(text)
        except (TypeError, ValueError):
            row = None
        if isinstance(row, dict) and row.get("path") == p:
            out[p] = row
        else:
            del texts[p]
    return out


def _listing(rows: dict[str, dict], files: int, read: int, removed: int, path: str, seconds: float = 0.0,
             texts: dict[str, str] | None = None) -> Listing:
    from velab.catalogue.liveness import settle

    ordered = [rows[p] for p in sorted(rows)]
    runs = [r for r in ordered if r.get("kind") != "other"]
    others = [r for r in ordered if r.get("kind") == "other"]
    texts = dict(texts or {})
    for p in settle(runs):  # now, not when indexed: a killed recorder's file never changes again
        texts.pop(p, None)  # its row is no longer the stored one
    return Listing(runs, others, files or len(rows), read, removed, seconds, path, texts)
