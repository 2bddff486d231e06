"""GUI: archive browser (open a run, stored fits, re-fit in the background, export), settings."""

from __future__ import annotations

import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pyqtgraph")

from velab.cli import main as velab_main  # noqa: E402

pytestmark = [pytest.mark.gui, pytest.mark.usefixtures("qt_cleanup")]


@pytest.fixture()
def settings(tmp_path):
    from velab.gui.main_window import make_settings

    return make_settings(tmp_path / "gui.ini")


@pytest.fixture(scope="module")
def synth_run(tmp_path_factory):
    path = tmp_path_factory.mktemp("runs") / "a.h5"
    assert velab_main(["synth", "--material", "A", "--duration", "5", "-o", str(path)]) == 0
    return path


@pytest.fixture()
def window(qtbot, settings):
    from velab.gui.app import ensure_app
    from velab.gui.main_window import MainWindow

    ensure_app()
    win = MainWindow(settings=settings)
    qtbot.addWidget(win)
    win.show()
    yield win
    win.close()


def test_open_refit_export(qtbot, window, synth_run, tmp_path):
    import shutil

    run = tmp_path / "run.h5"
    shutil.copy(synth_run, run)
    arch = window.archive
    window.tabs.setCurrentWidget(arch)
    with qtbot.waitSignal(arch.loaded, timeout=20000):
        arch.open(run)
    assert "material" in arch.summary.toPlainText()
    assert arch.run_plot.buffer.n == 6000
    assert arch.fit_combo.count() == 0

    arch.models_edit.setText("0-2")
    arch.window_spin.setValue(3.0)
    arch.starts_spin.setValue(2)
    progress = []
    arch.progress.valueChanged.connect(progress.append)
    with qtbot.waitSignal(arch.refitted, timeout=60000) as blocker:
        qtbot.mouseClick(arch.refit_button, __import__("PySide6.QtCore").QtCore.Qt.LeftButton)
        assert arch.busy and not arch.refit_button.isEnabled()  # the GUI thread is not fitting
    best = blocker.args[0]
    assert best in ("S1", "S2")
    assert progress and max(progress) >= 1
    qtbot.waitUntil(lambda: arch.fit_panel.best_name() == best, timeout=10000)
    assert arch.fit_panel.model_names() == ["EL", "S1", "S2"]
    qtbot.waitUntil(lambda: arch.fit_panel.data is not None, timeout=10000)
    assert set(arch.fit_panel.data["curves"]) == {"EL", "S1", "S2"}
    # stored in the file, listed, and shown again after a reload
    assert arch.fit_combo.findText("auto_w3s") >= 0
    with qtbot.waitSignal(arch.loaded, timeout=20000):
        arch.open(run)
    assert arch.fit_combo.currentText() == "auto_w3s"
    assert arch.fit_panel.best_name() == best

    csv = tmp_path / "run.csv"
    with qtbot.waitSignal(arch.exported, timeout=20000):
        arch.export_csv(csv)
    lines = csv.read_text().splitlines()
    assert lines[2].startswith("time_s,head_m,head_perturbation_m")
    assert len(lines) == 3 + 6000
    png = tmp_path / "fit.png"
    with qtbot.waitSignal(arch.exported, timeout=30000):
        arch.export_figure(png)
    assert png.stat().st_size > 10000
    assert any("Exported" in t for t in window.log.texts())


def test_refit_error_is_a_message(qtbot, window, synth_run):
    arch = window.archive
    with qtbot.waitSignal(arch.loaded, timeout=20000):
        arch.open(synth_run)
    arch.window_spin.setValue(3.0)
    arch.models_edit.setText("9")  # not a model
    arch.save_check.setChecked(False)
    arch.start_refit()
    qtbot.waitUntil(lambda: not arch.busy, timeout=20000)
    errors = window.log.texts("error")
    assert errors and "bad model list" in errors[-1]
    assert "Traceback" not in window.log.toPlainText()
    assert window.banner.isVisible() and "bad model list" in window.banner.text()


def test_open_bad_file_is_a_message(qtbot, window, tmp_path):
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"not hdf5")
    window.archive.open(bad)
    qtbot.waitUntil(lambda: bool(window.log.texts("error")), timeout=10000)
    assert "bad.h5" in window.log.texts("error")[-1]
    assert "Traceback" not in window.log.toPlainText()


def test_settings_persist(qtbot, tmp_path, synth_run):
    from velab.gui.app import ensure_app
    from velab.gui.main_window import MainWindow, make_settings

    ensure_app()
    ini = tmp_path / "persist.ini"
    win = MainWindow(settings=make_settings(ini))
    qtbot.addWidget(win)
    win.resize(760, 560)  # offscreen screens are 800 x 600
    win.run_panel.operator_edit.setText("Ada")
    win.archive.set_folder(synth_run.parent)
    win.tabs.setCurrentIndex(2)
    win.close()
    win2 = MainWindow(settings=make_settings(ini))
    qtbot.addWidget(win2)
    assert win2.run_panel.operator_edit.text() == "Ada"
    assert win2.tabs.currentIndex() == 2
    qtbot.waitUntil(lambda: win2.archive.files.count() >= 1, timeout=10000)  # listed on a worker thread
    assert (win2.width(), win2.height()) == (760, 560)
    win2.close()


def test_fits_a_laptop_screen(qtbot, settings):
    from velab.gui.app import ensure_app
    from velab.gui.main_window import MainWindow

    ensure_app()
    win = MainWindow(settings=settings)
    qtbot.addWidget(win)
    win.resize(1366, 700)
    win.show()
    qtbot.waitExposed(win)
    hint = win.minimumSizeHint()
    assert hint.width() <= 1366 and hint.height() <= 700
    win.close()


def test_gui_cli_without_qt_import():
    import subprocess
    import sys

    code = ("import sys; from velab.cli import build_parser; build_parser(); "
            "print(any(m.startswith('PySide6') for m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
