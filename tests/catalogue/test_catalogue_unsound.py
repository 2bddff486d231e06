"""`velab runs` lists an unsound run as damaged, with the reason, and counts it (issue 52).

A run whose structure is not a run's (velab.runfiles.soundness: its status deleted or bogus, its
format version, a NeXus class or the NXdata signal removed, its manoeuvre gone) opens, and used to
be listed under whatever status it still claimed ("recording" for a deleted status) with "0 damaged".
It is the run ``velab info`` names DAMAGED: the catalogue says ``damaged`` with the same defects, in
the table, the JSON row and the count, from a fresh index and from the stored rows alike.
"""

from __future__ import annotations

import hashlib
import json
import shutil

import h5py
import pytest

from velab.cli import main


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv("VELAB_CATALOGUE", raising=False)


def _set_status(value):
    def edit(fh):
        del fh["entry/status"]
        fh["entry/status"] = value
    return edit


# file name -> (the edit that makes it unsound, the defect its reason names)
UNSOUND = {
    "status_deleted.h5": (lambda fh: fh["entry"].__delitem__("status"), "no /entry/status"),
    "status_bogus.h5": (_set_status("bogus"), "'bogus'"),
    "no_version.h5": (lambda fh: fh.attrs.__delitem__("format_version"), "no @format_version"),
    "entry_class.h5": (lambda fh: fh["entry"].attrs.__delitem__("NX_class"), "no @NX_class on /entry"),
    "no_signal.h5": (lambda fh: fh["entry/data"].attrs.__delitem__("signal"), "no @signal on /entry/data"),
    "no_manoeuvre.h5": (lambda fh: fh["entry"].__delitem__("manoeuvre"), "no /entry/manoeuvre"),
}


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    p = tmp_path_factory.mktemp("unsound") / "base.h5"
    assert main(["synth", "--material", "A", "--duration", "1", "--rate", "200", "--title", "pipe X",
                 "-o", str(p)]) == 0
    return p


@pytest.fixture
def folder(tmp_path, base):
    d = tmp_path / "runs"
    d.mkdir()
    shutil.copy(base, d / "good.h5")
    for name, (edit, _) in UNSOUND.items():
        shutil.copy(base, d / name)
        with h5py.File(d / name, "r+") as fh:
            edit(fh)
    return d


def _digests(d) -> dict:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in d.iterdir()}


def _json(capsys, *argv) -> dict:
    capsys.readouterr()
    assert main(["runs", *map(str, argv), "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_unsound_runs_are_damaged_rows_with_their_reason(folder, capsys):
    before = _digests(folder)
    for attempt in ("fresh index", "from the index"):
        doc = _json(capsys, folder)
        assert doc["index"]["read"] == (len(UNSOUND) + 1 if attempt == "fresh index" else 0)
        by = {r["path"].rsplit("/", 1)[-1]: r for r in doc["runs"]}
        assert by["good.h5"]["status"] == "synthetic", attempt
        for name, (_, defect) in UNSOUND.items():
            row = by[name]
            assert row["status"] == "damaged", (attempt, name, row["status"])
            assert row["reason"].startswith("damaged run (") and defect in row["reason"], (attempt, row["reason"])
            assert "\n" not in row["reason"]
        # what is still readable of a damaged run stays in its row: the title, the rig
        assert by["no_manoeuvre.h5"]["title"] == "pipe X" and by["no_manoeuvre.h5"]["rig"]
    assert _digests(folder) == before  # listing never writes a run


def test_the_table_names_them_and_the_count_says_how_many(folder, capsys):
    capsys.readouterr()
    assert main(["runs", str(folder)]) == 0
    out = capsys.readouterr()
    n = len(UNSOUND)
    assert f"{n + 1} of {n + 1} runs shown ({n} damaged)" in out.err
    lines = [line for line in out.out.splitlines() if "damaged run (" in line]
    assert len(lines) == n
    for name, (_, defect) in UNSOUND.items():
        (line,) = [line for line in lines if f"{name}:" in line]
        assert " damaged " in line and defect in line, line
    # the filter finds them, and only them
    doc = _json(capsys, folder, "--status", "damaged")
    assert sorted(r["path"].rsplit("/", 1)[-1] for r in doc["runs"]) == sorted(UNSOUND)


def test_damaged_in_the_catalogue_exactly_when_info_says_damaged(folder, capsys):
    rows = {r["path"].rsplit("/", 1)[-1]: r for r in _json(capsys, folder)["runs"]}
    for name, row in rows.items():
        capsys.readouterr()
        code = main(["info", str(folder / name)])
        out = capsys.readouterr().out
        assert (row["status"] == "damaged") == (code == 2 and "DAMAGED" in out), (name, code, row["status"])
