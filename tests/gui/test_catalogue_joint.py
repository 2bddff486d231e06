"""The Archive tab's "Fit together": the joint fit (velab fit --joint) of the runs selected in the catalogue
table, on two real synthetic runs; copies of one run are not offered (the joint fit refuses a record twice)."""

from __future__ import annotations

import shutil

import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pyqtgraph")

from velab.cli import main  # noqa: E402

pytestmark = [pytest.mark.gui, pytest.mark.usefixtures("qt_cleanup")]


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv("VELAB_CATALOGUE", raising=False)


@pytest.fixture()
def archive(qtbot, tmp_path):
    from velab.gui.app import ensure_app
    from velab.gui.main_window import MainWindow, make_settings

    runs = tmp_path / "runs"
    runs.mkdir()
    for name, seed in (("a", 1), ("b", 2)):
        assert main(["synth", "--duration", "1", "--rate", "200", "--seed", str(seed), "--title", f"run {name}",
                     "-o", str(runs / f"{name}.h5"), "-q"]) == 0
    ensure_app()
    win = MainWindow(settings=make_settings(tmp_path / "gui.ini"))
    qtbot.addWidget(win)
    win.show()
    yield win.archive, runs
    win.close()


def _select_all(arch) -> None:
    from PySide6.QtCore import QItemSelectionModel

    for i in range(arch.catalogue.model.rowCount()):
        arch.catalogue.table.selectionModel().select(arch.catalogue.model.index(i, 0),
                                           QItemSelectionModel.Select | QItemSelectionModel.Rows)


def test_fit_together_from_the_table(qtbot, archive):
    from velab.gui.catalogue_view import JOINT_FIT_READY_TIP

    arch, runs = archive
    with qtbot.waitSignal(arch.indexed, timeout=60000):
        arch.set_folder(runs)
    arch.run.follow.setChecked(False)
    _select_all(arch)
    assert arch.catalogue.joint_fit_button.isEnabled() and arch.catalogue.joint_fit_button.toolTip() == JOINT_FIT_READY_TIP
    arch.fits.models_edit.setText("1")
    arch.fits.window_spin.setValue(0.9)
    with qtbot.waitSignal(arch.refitted, timeout=180000) as done:
        arch.catalogue.joint_fit_button.click()
    assert done.args == ["S1"]
    qtbot.waitUntil(lambda: all(arch.catalogue.model.row(i).get("fit_name") == "joint_w0.9s"
                                for i in range(arch.catalogue.model.rowCount())), timeout=60000)
    rows = [arch.catalogue.model.row(i) for i in range(2)]
    assert {r["best_model"] for r in rows} == {"S1"} and rows[0]["wave_speed_m_s"] == rows[1]["wave_speed_m_s"]
    assert rows[0]["wave_speed_m_s"] == pytest.approx(353.7, abs=5)


def test_copies_of_one_run_are_not_offered(qtbot, archive):
    from velab.gui.catalogue_view import JOINT_FIT_TIP

    arch, runs = archive
    (runs / "b.h5").unlink()
    shutil.copy(runs / "a.h5", runs / "a-copy.h5")
    with qtbot.waitSignal(arch.indexed, timeout=60000):
        arch.set_folder(runs)
    _select_all(arch)
    assert len(arch.catalogue.selected_rows()) == 2
    assert not arch.catalogue.joint_fit_button.isEnabled() and arch.catalogue.joint_fit_button.toolTip() == JOINT_FIT_TIP


def test_a_refused_joint_fit_is_one_message(qtbot, archive):
    """A window longer than the runs: the command's one-line error, named in the message log."""
    arch, runs = archive
    with qtbot.waitSignal(arch.indexed, timeout=60000):
        arch.set_folder(runs)
    arch.run.follow.setChecked(False)
    _select_all(arch)
    arch.fits.window_spin.setValue(30)
    errors = []
    arch.message.connect(lambda text, level: errors.append(text) if level in ("warning", "error") else None)
    arch.fits.fit_together(arch.catalogue.selected_runs())
    qtbot.waitUntil(lambda: bool(errors), timeout=120000)
    assert "window" in errors[0] and "\n" not in errors[0] and not arch.fits.busy
