"""A run being recorded against one whose recorder was killed: the catalogue tells them apart
(velab.catalogue.liveness) on a real `velab record --simulate` killed with SIGKILL."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from velab.catalogue.liveness import is_local
from velab.cli import main


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv("VELAB_CATALOGUE", raising=False)


def _runs(capsys, *args) -> dict:
    assert main(["runs", *map(str, args), "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def _recording(out_dir, capsys, timeout=60.0) -> dict:
    """The row of the run once the recorder has flushed samples into it."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if list(out_dir.glob("*.h5")):
            doc = _runs(capsys, out_dir)
            if doc["runs"] and (doc["runs"][0]["n_samples"] or 0) > 0:
                return doc["runs"][0]
        time.sleep(0.3)
    raise AssertionError("the recorder wrote no samples")


def test_live_recording_then_killed(tmp_path, capsys):
    out_dir = tmp_path / "runs"
    rec = subprocess.Popen([sys.executable, "-m", "velab.cli", "record", "--simulate", "--duration", "120",
                            "--pretrigger", "1", "--no-fit", "-q", "--title", "killed one", "--out-dir", str(out_dir)],
                           stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    try:
        live = _recording(out_dir, capsys)
        assert rec.poll() is None
        assert live["status"] == "recording" and "open" in live["flags"], live
        assert _runs(capsys, out_dir, "--status", "recording")["runs"]
    finally:
        os.killpg(rec.pid, signal.SIGKILL)  # the recorder and the simulated rig it started, at once
        rec.wait(timeout=30)
        rec.stderr.close()
    doc = _runs(capsys, out_dir)
    (row,) = doc["runs"]
    assert row["status"] == "interrupted", row
    assert "recording stopped at" in row["reason"] and "no writer holds it" in row["reason"]
    assert "velab recover" in row["reason"] and "\n" not in row["reason"]
    assert "open" in row["flags"] and row["title"] == "killed one" and row["n_samples"] > 0
    assert _runs(capsys, out_dir, "--status", "recording")["runs"] == []
    # the index still holds the row as read; the next listing decides again, from the index
    again = _runs(capsys, out_dir)
    assert again["index"]["read"] == 0 and again["runs"][0]["status"] == "interrupted"
    # the text table names it with its reason
    assert main(["runs", str(out_dir)]) == 0
    assert "interrupted" in capsys.readouterr().out
    # `velab recover` closes a copy: still not concluded, so interrupted, with the copy's own reason
    assert main(["recover", row["path"], "-q"]) == 0
    capsys.readouterr()
    rows = {os.path.basename(r["path"]): r for r in _runs(capsys, out_dir)["runs"]}
    (copy,) = [r for name, r in rows.items() if ".recovered." in name]
    assert copy["status"] == "interrupted" and "recovered copy" in copy["reason"] and "open" not in copy["flags"]


def test_a_live_writer_holding_a_quiet_file_is_recording(tmp_path, capsys):
    """Liveness is the writer's open file, not the file's age: a writer that has not flushed for long is live."""
    writer = (
        "import sys, numpy as np\n"
        "from velab.config import load_rig\n"
        "from velab.runfiles import RunWriter\n"
        "w = RunWriter(sys.argv[1], load_rig('perugia'), sample_rate_hz=1000.0, title='quiet')\n"
        "t = np.arange(100) / 1000.0\n"
        "w.append(t, head=30 + t); w.flush()\n"
        "print('flushed', flush=True); sys.stdin.readline(); w.close('completed')\n"
    )
    path = tmp_path / "quiet.h5"
    proc = subprocess.Popen([sys.executable, "-c", writer, str(path)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            text=True)
    try:
        assert proc.stdout.readline().strip() == "flushed"
        old = time.time() - 3600
        os.utime(path, (old, old))  # as if the last flush were an hour ago
        (row,) = _runs(capsys, tmp_path)["runs"]
        assert row["status"] == "recording", row
    finally:
        proc.stdin.write("\n")
        proc.stdin.close()
        proc.wait(timeout=30)
    (row,) = _runs(capsys, tmp_path)["runs"]
    assert row["status"] == "completed"


def test_network_file_systems_wait_for_the_quiet_time():
    mounts = [("/srv/lab", "nfs4"), ("/", "ext4")]
    assert is_local("/tmp/x.h5", mounts) and not is_local("/srv/lab/runs/x.h5", mounts)
    assert not is_local("/anything", [])  # unknown: not taken for local


def test_the_archive_tab_shows_a_killed_writer_as_interrupted(qtbot, tmp_path):
    pytest.importorskip("PySide6")
    pytest.importorskip("pyqtgraph")
    from PySide6.QtCore import Qt

    from velab.gui.app import ensure_app
    from velab.gui.main_window import MainWindow, make_settings

    writer = (
        "import sys, numpy as np\n"
        "from velab.config import load_rig\n"
        "from velab.runfiles import RunWriter\n"
        "w = RunWriter(sys.argv[1], load_rig('perugia'), sample_rate_hz=1000.0, title='killed')\n"
        "t = np.arange(100) / 1000.0\n"
        "w.append(t, head=30 + t); w.flush()\n"
        "print('flushed', flush=True); sys.stdin.readline()\n"
    )
    runs = tmp_path / "runs"
    runs.mkdir()
    proc = subprocess.Popen([sys.executable, "-c", writer, str(runs / "killed.h5")], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "flushed"
    proc.kill()
    proc.wait(timeout=30)
    ensure_app()
    win = MainWindow(settings=make_settings(tmp_path / "gui.ini"))
    qtbot.addWidget(win)
    win.show()
    try:
        arch = win.archive
        with qtbot.waitSignal(arch.indexed, timeout=60000):
            arch.set_folder(runs)
        assert arch.catalogue.model.rowCount() == 1
        assert arch.catalogue.model.data(arch.catalogue.model.index(0, 1)).startswith("interrupted")
        tip = arch.catalogue.model.data(arch.catalogue.model.index(0, 0), Qt.ToolTipRole)
        assert "no writer holds it" in tip and "velab recover" in tip
        arch.catalogue.status_filter.setCurrentText("interrupted")
        qtbot.waitUntil(lambda: arch.catalogue.model.rowCount() == 1, timeout=5000)
        arch.catalogue.status_filter.setCurrentText("recording")
        qtbot.waitUntil(lambda: arch.catalogue.model.rowCount() == 0, timeout=5000)
    finally:
        win.close()
