"""The run catalogue (velab.catalogue, `velab runs`) on real run files: recorded, synthetic, imported,
damaged, a non-run HDF5 file, a run being written, in nested folders; the index kept in the cache."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import textwrap
import time

import h5py
import numpy as np
import pytest

from velab.cli import main

ENV_ROOT = "VELAB_CATALOGUE"


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    """Every test its own user cache (the index's default place)."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv(ENV_ROOT, raising=False)


@pytest.fixture(scope="module")
def sources(tmp_path_factory):
    """One file of each kind, made once by the real commands."""
    d = tmp_path_factory.mktemp("sources")
    synth = d / "synth.h5"
    assert main(["synth", "--material", "A", "--duration", "1", "--rate", "200", "--title", "pipe X day 1",
                 "-o", str(synth)]) == 0
    fitted = d / "fitted.h5"
    shutil.copy(synth, fitted)
    assert main(["fit", str(fitted), "--models", "0-2", "--window", "0.9", "--starts", "2", "-q"]) == 0
    csv = d / "rec.csv"
    t = np.arange(-100, 400) * 0.002
    with open(csv, "w") as fh:
        fh.write("time_s,p_bar\n")
        fh.writelines(f"{float(a)!r},{float(3.4 + 0.5 * np.sin(9 * a) * (a >= 0))!r}\n" for a in t)
    imported = d / "imported.h5"
    assert main(["import", str(csv), "--rig", "perugia", "--units", "bar", "-o", str(imported)]) == 0
    rec_dir = d / "rec"
    assert main(["record", "--simulate", "--fast", "--duration", "2", "--pretrigger", "1", "--no-fit", "-q",
                 "--title", "bench run", "--operator", "Ada", "--specimen", "PX-7", "--notes", "after repair",
                 "--out-dir", str(rec_dir)]) == 0
    (recorded,) = rec_dir.glob("*.h5")
    return {"synth": synth, "fitted": fitted, "imported": imported, "recorded": recorded}


WRITER = textwrap.dedent(
    """
    import sys, numpy as np
    from velab.config import load_rig
    from velab.runfiles import RunWriter
    w = RunWriter(sys.argv[1], load_rig("perugia"), sample_rate_hz=1000.0, title="live one")
    for i in range(5):
        t = np.arange(i * 100, (i + 1) * 100) / 1000.0
        w.append(t, head=30 + t)
        w.flush()
    print("flushed", flush=True)
    sys.stdin.readline()
    w.close("completed")
    """
)


@pytest.fixture()
def archive(tmp_path, sources):
    """Nested dated folders with every kind of file, and a recorder still writing one."""
    root = tmp_path / "archive"
    (root / "2026" / "11-20").mkdir(parents=True)
    (root / "2026" / "11-21" / "pump").mkdir(parents=True)
    shutil.copy(sources["synth"], root / "2026" / "11-20" / "synth.h5")
    shutil.copy(sources["fitted"], root / "2026" / "11-20" / "fitted.h5")
    shutil.copy(sources["imported"], root / "2026" / "11-21" / "imported.h5")
    shutil.copy(sources["recorded"], root / "2026" / "11-21" / "pump" / "recorded.h5")
    data = sources["synth"].read_bytes()
    (root / "2026" / "truncated.h5").write_bytes(data[: len(data) // 3])
    (root / "2026" / "garbage.h5").write_bytes(b"not an HDF5 file at all")
    (root / "2026" / "empty.nxs").write_bytes(b"")
    with h5py.File(root / "2026" / "other.h5", "w") as f:
        f["x"] = np.arange(3)
    (root / "2026" / ".hidden.h5.part").write_bytes(data)  # a writer's temporary file: not a run yet
    (root / "notes.txt").write_text("not a run")
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(root / "live.h5")], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "flushed"
    yield root
    if proc.poll() is None:
        proc.stdin.write("\n")
        proc.stdin.flush()
        proc.wait(timeout=30)


def _runs(capsys, *args) -> tuple[int, dict]:
    rc = main(["runs", *map(str, args), "--json"])
    out = capsys.readouterr().out
    return rc, json.loads(out)


def _by_name(doc) -> dict:
    return {os.path.basename(r["path"]): r for r in doc["runs"]}


def _digest(root) -> dict:
    return {str(p): (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
            for p in sorted(root.rglob("*")) if p.is_file() and p.name != "live.h5"}


def test_lists_every_kind_of_file(archive, capsys):
    before = _digest(archive)
    rc, doc = _runs(capsys, archive)
    assert rc == 0
    rows = _by_name(doc)
    assert set(rows) == {"synth.h5", "fitted.h5", "imported.h5", "recorded.h5", "truncated.h5", "garbage.h5",
                         "empty.nxs", "live.h5"}
    assert [os.path.basename(r["path"]) for r in doc["not_runs"]] == ["other.h5"]
    assert "not a velab run file" in doc["not_runs"][0]["reason"]
    # the damaged ones: named, with the reader's one-line reason
    for name in ("truncated.h5", "garbage.h5", "empty.nxs"):
        r = rows[name]
        assert r["status"] == "damaged" and r["reason"] and "\n" not in r["reason"], r
    assert "not an HDF5 file" in rows["garbage.h5"]["reason"]
    # a run being written
    live = rows["live.h5"]
    assert live["status"] == "recording" and "open" in live["flags"] and live["n_samples"] == 500
    # the recorded run: the operator's metadata, measured flow, no fit
    rec = rows["recorded.h5"]
    assert (rec["status"], rec["title"], rec["operator"], rec["specimen"], rec["notes"]) == \
        ("completed", "bench run", "Ada", "PX-7", "after repair")
    assert rec["source"] == "recording" and rec["sample_rate_hz"] == 1000.0
    assert rec["measured_flow_l_s"] == pytest.approx(3.64, rel=0.05)
    assert rec["duration_s"] == pytest.approx(2.0, abs=0.05) and rec["n_fits"] == 0 and rec["best_model"] is None
    # the fitted synthetic run: the latest fit's best model, wave speed +- SE, elements
    fit = rows["fitted.h5"]
    assert fit["n_fits"] == 1 and fit["best_model"] in ("S1", "S2")
    assert fit["wave_speed_m_s"] == pytest.approx(353.7, abs=5) and fit["wave_speed_se_m_s"] > 0
    assert fit["misfit"] is False and len(fit["elements"]) == int(fit["best_model"][1])
    assert all(e["J_per_pa"] > 0 and e["tau_s"] > 0 for e in fit["elements"])
    syn = rows["synth.h5"]
    assert (syn["status"], syn["source"], syn["material"], syn["title"]) == ("synthetic", "synth", "A", "pipe X day 1")
    assert (syn["beta_per_s"], syn["steady_flow_l_s"], syn["sample_rate_hz"]) == (32.0, pytest.approx(3.64), 200.0)
    assert rows["imported.h5"]["status"] == "imported" and rows["imported.h5"]["rig"].startswith("Perugia")
    # sorted by start time, damaged files (no start time) last; never a run file written
    starts = [r["start_time"] for r in doc["runs"] if r["start_time"]]
    assert starts == sorted(starts) and doc["runs"][-1]["status"] == "damaged"
    assert _digest(archive) == before
    assert doc["index"]["read"] == 9 and doc["index"]["path"].startswith(os.environ["XDG_CACHE_HOME"])


def test_second_listing_reads_only_what_changed(archive, sources, capsys):
    _, first = _runs(capsys, archive)
    _, again = _runs(capsys, archive)
    assert again["index"]["read"] <= 1  # nothing changed (the live run is read again if it grew)
    # a new run, a removed one, a run given a second fit (saved by copy and rename: a new inode)
    shutil.copy(sources["fitted"], archive / "2026" / "11-21" / "new.h5")
    (archive / "2026" / "11-20" / "synth.h5").unlink()
    assert main(["fit", str(archive / "2026" / "11-20" / "fitted.h5"), "--models", "0-1", "--window", "0.5",
                 "--starts", "1", "--name", "second", "-q"]) == 0
    capsys.readouterr()
    _, doc = _runs(capsys, archive)
    rows = _by_name(doc)
    assert "new.h5" in rows and "synth.h5" not in rows
    assert rows["fitted.h5"]["n_fits"] == 2 and rows["fitted.h5"]["fit_name"] == "second"
    assert rows["fitted.h5"]["best_model"] in ("EL", "S1")
    assert doc["index"]["removed"] == 1 and doc["index"]["read"] <= 3  # new, fitted (and the live run)


def test_filters_and_sort(archive, capsys):
    rc, doc = _runs(capsys, archive, "--best", "S1,S2", "--since", "2020-01-01", "--text", "PIPE")
    assert rc == 0 and [os.path.basename(r["path"]) for r in doc["runs"]] == ["fitted.h5"]
    _, doc = _runs(capsys, archive, "--text", "ada", "--text", "repair")
    assert [os.path.basename(r["path"]) for r in doc["runs"]] == ["recorded.h5"]
    _, doc = _runs(capsys, archive, "--best", "none", "--status", "synthetic,imported")
    assert sorted(os.path.basename(r["path"]) for r in doc["runs"]) == ["imported.h5", "synth.h5"]
    _, doc = _runs(capsys, archive, "--status", "damaged", "--sort=-path")
    assert [os.path.basename(r["path"]) for r in doc["runs"]] == ["truncated.h5", "garbage.h5", "empty.nxs"]
    _, doc = _runs(capsys, archive, "--until", "2020-01-01")
    assert doc["runs"] == []  # every run started today; damaged files go by their mtime
    _, doc = _runs(capsys, archive, "--rig", "perugia", "--status", "recording")
    assert [os.path.basename(r["path"]) for r in doc["runs"]] == ["live.h5"]
    _, doc = _runs(capsys, archive, "--sort=-wave-speed")
    assert os.path.basename(doc["runs"][0]["path"]) == "fitted.h5"
    for bad, what in ((["--status", "done"], "--status done: not a status"), (["--since", "yesterday"], "--since"),
                      (["--sort", "colour"], "--sort colour")):
        assert main(["runs", str(archive), *bad]) == 2
        err = capsys.readouterr().err
        assert what in err and len(err.strip().splitlines()) == 1, err
    with pytest.raises(SystemExit) as exc:  # argparse's own: one line, exit 2
        main(["runs", str(archive), "--jobs", "0"])
    assert exc.value.code == 2 and "--jobs: must be an integer" in capsys.readouterr().err
    assert main(["runs", str(archive / "nowhere")]) == 2
    assert "no such folder" in capsys.readouterr().err


def test_text_and_csv_forms(archive, capsys):
    assert main(["runs", str(archive)]) == 0
    out, err = capsys.readouterr()
    lines = out.splitlines()
    assert lines[0].startswith("start") and len(lines) == 1 + 8
    assert any("garbage.h5: not an HDF5 file" in ln for ln in lines)
    assert any("bench run / Ada / PX-7" in ln and "2026/11-21/pump/recorded.h5" in ln for ln in lines)
    assert "8 of 8 runs shown (3 damaged, 1 HDF5 file(s) that are not runs skipped)" in err
    assert main(["runs", str(archive), "--csv", "--status", "completed"]) == 0
    import csv
    rows = list(csv.DictReader(capsys.readouterr().out.splitlines()))
    assert len(rows) == 1 and rows[0]["operator"] == "Ada" and rows[0]["status"] == "completed"


def test_damaged_index_is_rebuilt(archive, capsys, tmp_path):
    index = tmp_path / "cache" / "velab" / "catalogue.sqlite"
    _runs(capsys, archive)
    assert index.is_file()
    index.write_bytes(b"this is not an SQLite file" * 100)
    for suffix in ("-wal", "-shm"):
        (tmp_path / "cache" / "velab" / ("catalogue.sqlite" + suffix)).unlink(missing_ok=True)
    rc, doc = _runs(capsys, archive)
    assert rc == 0 and len(doc["runs"]) == 8 and doc["index"]["read"] == 9
    assert index.read_bytes().startswith(b"SQLite format 3")


def test_index_beside_the_archive_when_the_cache_cannot_be_written(archive, capsys, tmp_path, monkeypatch):
    blocked = tmp_path / "blocked"
    blocked.write_text("a file where the cache folder would be")
    monkeypatch.setenv("XDG_CACHE_HOME", str(blocked))
    _, doc = _runs(capsys, archive)
    assert doc["index"]["path"] == str(archive / ".velab-catalogue.sqlite") and len(doc["runs"]) == 8
    _, doc = _runs(capsys, archive)
    assert doc["index"]["read"] <= 1  # kept there (the live run may be read again)


def test_two_listings_at_once_while_a_recorder_writes(archive, tmp_path):
    env = dict(os.environ)
    cmd = [sys.executable, "-m", "velab.cli", "runs", str(archive), "--json"]
    procs = [subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
             for _ in range(2)]
    outs = [p.communicate(timeout=120) for p in procs]
    for p, (out, err) in zip(procs, outs):
        assert p.returncode == 0, err
        doc = json.loads(out)
        assert len(doc["runs"]) == 8 and sum(r["status"] == "damaged" for r in doc["runs"]) == 3
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0 and json.loads(out.stdout)["index"]["read"] <= 1


def test_a_file_that_makes_hdf5_loop_is_damaged_within_the_deadline(tmp_path):
    """The fuzz's zeroed object headers make HDF5 itself loop forever (tests/runfiles/test_runfile_fuzz.py)."""
    from velab.catalogue.index import Catalogue

    base = tmp_path / "base.h5"
    assert main(["synth", "--duration", "1", "--pretrigger", "0.2", "-o", str(base), "-q"]) == 0
    data = base.read_bytes()
    (tmp_path / "loops.h5").write_bytes(data[:4625] + bytes(483) + data[5108:])
    t0 = time.monotonic()
    with Catalogue(tmp_path / "index.sqlite") as cat:
        listing = cat.update([tmp_path], deadline_s=3.0)
    rows = {os.path.basename(r["path"]): r for r in listing.rows}
    assert time.monotonic() - t0 < 60
    assert rows["base.h5"]["status"] == "synthetic"
    assert rows["loops.h5"]["status"] == "damaged"
    assert "does not finish" in rows["loops.h5"]["reason"] or "damaged" in rows["loops.h5"]["reason"]


def _copies(root, source, n: int) -> list:
    """n distinct runs in nested dated folders: copies of one file, each given its own title and start."""
    from velab.runfiles import layout as L

    paths = []
    for i in range(n):
        d = root / f"2026-{1 + i // 250:02d}" / f"day{(i // 25) % 10}"
        d.mkdir(parents=True, exist_ok=True)
        p = d / f"run{i:04d}.h5"
        shutil.copy(source, p)
        with h5py.File(p, "r+") as f:  # test set-up editing its own copies
            L.set_str(f["entry"], "title", f"pipe {'X' if i % 2 else 'Y'} batch {i}")
            L.set_str(f["entry"], "start_time", f"2026-{1 + i // 250:02d}-{1 + i % 28:02d}T10:00:00+00:00")
        paths.append(p)
    return paths


def test_a_thousand_runs(tmp_path, sources, capsys):
    root = tmp_path / "big"
    _copies(root, sources["fitted"], 1000)
    (root / "2026-01" / "broken.h5").write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(100))
    with h5py.File(root / "2026-02" / "table.h5", "w") as f:
        f["t"] = np.arange(10)
    t0 = time.perf_counter()
    rc, doc = _runs(capsys, root)
    first = time.perf_counter() - t0
    assert rc == 0 and len(doc["runs"]) == 1001 and len(doc["not_runs"]) == 1
    assert [r["status"] for r in doc["runs"]].count("damaged") == 1
    keys = {"path", "start_time", "title", "operator", "specimen", "rig", "steady_flow_l_s", "beta_per_s",
            "sample_rate_hz", "duration_s", "status", "flags", "best_model", "wave_speed_m_s", "wave_speed_se_m_s",
            "misfit", "n_fits"}
    assert all(keys <= set(r) for r in doc["runs"])
    shutil.copy(sources["synth"], root / "2026-04" / "added.h5")
    t0 = time.perf_counter()
    rc, doc = _runs(capsys, root)
    second = time.perf_counter() - t0
    assert rc == 0 and doc["index"]["read"] == 1 and any(r["path"].endswith("added.h5") for r in doc["runs"])
    rc, doc = _runs(capsys, root, "--best", doc["runs"][0]["best_model"], "--since", "2026-03-01", "--text", "pipe x")
    assert len(doc["runs"]) == 250 and all("pipe X" in r["title"] for r in doc["runs"])
    assert all(r["start_time"] >= "2026-03" for r in doc["runs"])
    print(f"1,000 runs: first listing {first:.1f} s, after adding one {second:.2f} s")  # figures, not assertions
