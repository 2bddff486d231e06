"""The catalogue's SQLite index under concurrency: several `velab runs` processes opening one fresh index
at the same instant (the CI failure "no such table: files": a "database is locked" taken for damage made
one process delete the index another was creating), and an index damaged or rebuilt under a listing."""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
import subprocess
import sys
import textwrap
import time

import pytest

from velab.cli import main

# the real command in a real process, its imports done first so that every process opens the fresh
# index at the same instant (a start time given on the command line): the race, not the import jitter
AT_ONCE = textwrap.dedent(
    """
    import sys, time
    from velab.cli import main
    import velab.catalogue.index, velab.catalogue.query, velab.commands.runs  # noqa: F401
    start = float(sys.argv[1])
    time.sleep(max(0.0, start - time.time()))
    sys.exit(main(sys.argv[2:]))
    """
)


@pytest.fixture(scope="module")
def small_archive(tmp_path_factory):
    root = tmp_path_factory.mktemp("small")
    src = root / "a" / "one.h5"
    src.parent.mkdir()
    assert main(["synth", "--duration", "0.5", "--rate", "200", "--title", "hammer", "-o", str(src), "-q"]) == 0
    for i in range(3):
        d = root / ("a" if i % 2 else "b") / f"d{i}"
        d.mkdir(parents=True)
        shutil.copy(src, d / f"copy{i}.h5")
    (root / "b" / "broken.h5").write_bytes(b"not an HDF5 file")
    return root


def _at_once(n: int, index, root, extra=()) -> list[tuple[int, str, str]]:
    start = time.time() + 3.0  # every child imported by then, on a loaded 2-core machine too
    env = dict(os.environ, VELAB_CATALOGUE=str(index))
    procs = [subprocess.Popen([sys.executable, "-c", AT_ONCE, repr(start), "runs", str(root), "--json", *extra],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
             for _ in range(n)]
    outs = [p.communicate(timeout=120) for p in procs]
    return [(p.returncode, *o) for p, o in zip(procs, outs)]


def _check(results, n_runs: int = 5) -> None:
    for rc, out, err in results:
        assert rc == 0, err
        doc = json.loads(out)
        assert len(doc["runs"]) == n_runs, doc["runs"]
        assert sum(r["status"] == "damaged" for r in doc["runs"]) == 1
        assert "Traceback" not in err and "not kept" not in err, err


@pytest.mark.parametrize("round_", range(3))
def test_many_listings_open_a_fresh_index_at_once(small_archive, tmp_path, round_):
    index = tmp_path / "fresh.sqlite"
    results = _at_once(5, index, small_archive)
    _check(results)
    # the index survived them all: complete, and the next listing reads nothing
    with sqlite3.connect(index) as db:
        assert db.execute("SELECT count(*) FROM files").fetchone()[0] == 5
    env = dict(os.environ, VELAB_CATALOGUE=str(index))
    out = subprocess.run([sys.executable, "-m", "velab.cli", "runs", str(small_archive), "--json"],
                         capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0 and json.loads(out.stdout)["index"]["read"] == 0


def test_many_listings_on_a_damaged_index_at_once(small_archive, tmp_path):
    """Each finds the file damaged; one rebuilds it, the others use that one (not delete it again)."""
    index = tmp_path / "damaged.sqlite"
    index.write_bytes(b"this is not an SQLite file" * 200)
    _check(_at_once(4, index, small_archive))
    assert index.read_bytes().startswith(b"SQLite format 3")
    with sqlite3.connect(index) as db:
        assert db.execute("SELECT count(*) FROM files").fetchone()[0] == 5


def test_another_version_is_replaced_once(small_archive, tmp_path):
    """An index of another schema version: dropped and made again in one transaction, not per process."""
    index = tmp_path / "old.sqlite"
    with sqlite3.connect(index) as db:
        db.execute("CREATE TABLE files (path TEXT PRIMARY KEY, whatever TEXT)")
        db.execute("PRAGMA user_version=1")
    _check(_at_once(4, index, small_archive))
    from velab.catalogue.index import _version

    with sqlite3.connect(index) as db:
        assert db.execute("PRAGMA user_version").fetchone()[0] == _version()
        assert db.execute("SELECT count(*) FROM files").fetchone()[0] == 5


def test_the_table_dropped_under_an_open_catalogue(small_archive, tmp_path):
    """Another process made the index anew between our open and our write: opened again, rows kept."""
    from velab.catalogue.index import Catalogue

    index = tmp_path / "index.sqlite"
    with Catalogue(index) as cat:
        with sqlite3.connect(index) as other:
            other.execute("DROP TABLE files")
        listing = cat.update([small_archive], jobs=1)
        assert len(listing.rows) == 5
    with sqlite3.connect(index) as db:
        assert db.execute("SELECT count(*) FROM files").fetchone()[0] == 5


def test_a_locked_fresh_index_is_waited_for_not_deleted(small_archive, tmp_path, monkeypatch):
    """Another process is setting up the same fresh file (rollback journal, exclusive lock) past the busy
    timeout: "database is locked" is retried, never taken for damage (the old code deleted the file here)."""
    import threading

    import velab.catalogue.index as ix

    index = tmp_path / "fresh.sqlite"
    monkeypatch.setattr(ix, "BUSY_TIMEOUT_MS", 100)  # the lock outlasts the timeout: the retries must cover it
    holder = sqlite3.connect(index, isolation_level=None, check_same_thread=False)
    holder.execute("BEGIN EXCLUSIVE")
    holder.execute("CREATE TABLE setting_up (x)")
    inode = index.stat().st_ino
    release = threading.Timer(0.6, lambda: (holder.execute("ROLLBACK"), holder.close()))
    release.start()
    try:
        with ix.Catalogue(index) as cat:
            assert cat.path == str(index)  # not fallen back to memory
            listing = cat.update([small_archive], jobs=1)
    finally:
        release.join()
    assert len(listing.rows) == 5 and index.stat().st_ino == inode
    with sqlite3.connect(index) as db:
        assert db.execute("SELECT count(*) FROM files").fetchone()[0] == 5


def test_a_busy_index_is_not_deleted(small_archive, tmp_path, monkeypatch):
    """Held by a writer past our patience: listed without keeping the rows, and the index left as it was."""
    import velab.catalogue.index as ix

    index = tmp_path / "held.sqlite"
    with ix.Catalogue(index) as cat:
        cat.update([small_archive], jobs=1)
    inode = index.stat().st_ino
    monkeypatch.setattr(ix, "BUSY_TIMEOUT_MS", 200)  # not 30 s of waiting in a test
    holder = sqlite3.connect(index, isolation_level=None)
    holder.execute("BEGIN EXCLUSIVE")
    try:
        with ix.Catalogue(index) as cat:
            listing = cat.update([small_archive], jobs=1, rebuild=True)
        assert len(listing.rows) == 5
    finally:
        holder.execute("ROLLBACK")
        holder.close()
    assert index.stat().st_ino == inode
    with sqlite3.connect(index) as db:
        assert db.execute("SELECT count(*) FROM files").fetchone()[0] == 5


def test_an_index_replaced_under_an_open_catalogue(small_archive, tmp_path):
    """Another process deleted a damaged index and made a new one: our rows go into the new file, not the deleted."""
    from velab.catalogue.index import Catalogue

    index = tmp_path / "index.sqlite"
    with Catalogue(index) as cat:
        for suffix in ("", "-wal", "-shm"):
            (tmp_path / ("index.sqlite" + suffix)).unlink(missing_ok=True)
        Catalogue(index).close()  # the other process's fresh, empty index
        assert len(cat.update([small_archive], jobs=1).rows) == 5
    with sqlite3.connect(index) as db:
        assert db.execute("SELECT count(*) FROM files").fetchone()[0] == 5
