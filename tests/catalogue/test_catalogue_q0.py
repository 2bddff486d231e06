"""The steady-flow filter: `velab runs --q0` and the Archive tab's Q0 field ("which runs of pipe X at 3.6 l/s
gave S3"), on real synthetic runs whose copies were given other steady flows."""

from __future__ import annotations

import json
import os
import shutil

import h5py
import pytest

from velab.catalogue.query import parse_range
from velab.cli import main

FLOWS = {"q2.h5": 2.0, "q36.h5": 3.6, "q37.h5": 3.7, "q5.h5": 5.0}  # l/s


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv("VELAB_CATALOGUE", raising=False)


@pytest.fixture(scope="module")
def flows(tmp_path_factory):
    root = tmp_path_factory.mktemp("flows")
    src = root / "src.h5"
    assert main(["synth", "--duration", "0.5", "--rate", "200", "--title", "pipe X", "-o", str(src), "-q"]) == 0
    arch = root / "archive"
    (arch / "sub").mkdir(parents=True)
    for name, q in FLOWS.items():
        p = arch / "sub" / name
        shutil.copy(src, p)
        with h5py.File(p, "r+") as f:  # the test's own copies: another steady flow (stored in m3/s)
            f["entry/manoeuvre/steady_flow"][()] = q / 1e3
    (arch / "broken.h5").write_bytes(b"not HDF5")  # no flow: never matches a --q0 filter
    src.unlink()
    return arch


def _names(capsys, *args) -> list[str]:
    assert main(["runs", *map(str, args), "--json", "--sort", "q0"]) == 0
    return [os.path.basename(r["path"]) for r in json.loads(capsys.readouterr().out)["runs"]]


def test_q0_filter(flows, capsys):
    assert _names(capsys, flows, "--q0", "3.6") == ["q36.h5", "q37.h5"]  # 3.6 +- 3 %
    assert _names(capsys, flows, "--q0", "3.6~0.05") == ["q36.h5"]
    assert _names(capsys, flows, "--q0", "3.7:") == ["q37.h5", "q5.h5"]  # bounds included
    assert _names(capsys, flows, "--q0", "3:") == ["q36.h5", "q37.h5", "q5.h5"]
    assert _names(capsys, flows, "--q0", ":3.65") == ["q2.h5", "q36.h5"]
    assert _names(capsys, flows, "--q0", "2:5", "--text", "pipe x", "--status", "synthetic") == list(FLOWS)
    assert _names(capsys, flows, "--q0", "6:9") == []
    for bad, what in (("fast", "use MIN:MAX"), ("4:3", "MIN 4 is above MAX 3"), (":", "at least one bound"),
                      ("1~-1", "use MIN:MAX"), ("inf:", "finite")):
        assert main(["runs", str(flows), f"--q0={bad}"]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"velab: --q0: not a range: '{bad}'") and what in err, err
        assert len(err.strip().splitlines()) == 1


def test_parse_range():
    assert parse_range("3.4:3.8") == (3.4, 3.8) and parse_range(" 1 : ") == (1.0, None)
    lo, hi = parse_range("3.6")
    assert lo == pytest.approx(3.492) and hi == pytest.approx(3.708)


def test_the_archive_tab_filters_on_q0(qtbot, flows, tmp_path):
    pytest.importorskip("PySide6")
    pytest.importorskip("pyqtgraph")
    from velab.gui.app import ensure_app
    from velab.gui.main_window import MainWindow, make_settings

    ensure_app()
    win = MainWindow(settings=make_settings(tmp_path / "gui.ini"))
    qtbot.addWidget(win)
    win.show()
    try:
        arch = win.archive
        with qtbot.waitSignal(arch.indexed, timeout=60000):
            arch.set_folder(flows)
        assert arch.catalogue.model.rowCount() == 5
        arch.catalogue.q0_filter.setText("3.6")
        qtbot.waitUntil(lambda: arch.catalogue.model.rowCount() == 2, timeout=5000)
        assert {os.path.basename(arch.catalogue.model.row(i)["path"]) for i in range(2)} == {"q36.h5", "q37.h5"}
        arch.catalogue.q0_filter.setText(":2.5")
        qtbot.waitUntil(lambda: arch.catalogue.model.rowCount() == 1, timeout=5000)
        arch.catalogue.q0_filter.setText("4:3")  # marked, named, and ignored
        qtbot.waitUntil(lambda: arch.catalogue.model.rowCount() == 5, timeout=5000)
        assert "above MAX" in arch.catalogue.q0_filter.toolTip() and "color" in arch.catalogue.q0_filter.styleSheet()  # marked bad
        arch.catalogue.q0_filter.setText("")
        qtbot.waitUntil(lambda: "MIN:MAX" in arch.catalogue.q0_filter.toolTip(), timeout=5000)
    finally:
        win.close()


def test_the_index_columns_cover_every_filter_and_sort_field():
    """A listing filters and sorts the light rows (no JSON decoded): they must carry every field used."""
    from velab.catalogue.index import LIGHT
    from velab.catalogue.query import FILTER_FIELDS, SORT_KEYS

    assert set(FILTER_FIELDS) | set(SORT_KEYS.values()) <= set(LIGHT) | {"path"}


def test_light_and_whole_listings_agree(flows, capsys, tmp_path):
    """The JSON document (stored texts copied) and the CSV (rows decoded) of the same filtered, sorted listing."""
    import csv

    from velab.catalogue.rows import COLUMNS

    assert main(["runs", str(flows), "--json", "--q0", "3:", "--sort=-q0"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert main(["runs", str(flows), "--csv", "--q0", "3:", "--sort=-q0"]) == 0
    rows = list(csv.DictReader(capsys.readouterr().out.splitlines()))
    assert [r["path"] for r in rows] == [r["path"] for r in doc["runs"]] and len(rows) == 3
    assert all(set(r) == set(COLUMNS) for r in doc["runs"])  # every column, not only the light ones
    assert [float(r["steady_flow_l_s"]) for r in rows] == [r["steady_flow_l_s"] for r in doc["runs"]]
