"""A window that fits a lab laptop (issue 12, item 6): every control of a run visible at 1366 x 768,
value fields that ignore the mouse wheel unless focused, every model row of the fit table on screen,
J-tau labels that do not overlap, and the fitter's per-model findings (bounds, negligible elements,
uncertainties) in the table."""

from __future__ import annotations

import copy

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pyqtgraph")

from gui_operator import make_window  # noqa: E402

from velab.cli import main as velab_main  # noqa: E402

pytestmark = [pytest.mark.gui, pytest.mark.usefixtures("qt_cleanup")]


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    """A real sweep of EL..S6 and the reduced S1r..S5r (12 rows) on a synthetic run of material A."""
    from velab.fitting import fit_sweep
    from velab.runfiles import read_run

    path = tmp_path_factory.mktemp("runs") / "a.h5"
    assert velab_main(["synth", "--material", "A", "--duration", "4", "--friction", "linear", "--valve", "imposed", "-o", str(path)]) == 0
    run = read_run(path)
    t, h = run.fit_window(3.0)
    return t, h, run.rig, fit_sweep(t, h, run.rig, models=range(7), window_s=3.0, reduced=True, starts=1, polish=False)


def _fully_visible(w, win) -> bool:
    """On screen, not clipped by a scroll area or a parent, inside the window."""
    from PySide6.QtCore import QRect

    if not w.isVisible():
        return False
    if w.visibleRegion().boundingRect() != w.rect():
        return False
    top_left = w.mapTo(win, w.rect().topLeft())
    return win.rect().contains(QRect(top_left, w.size()))


@pytest.mark.parametrize("size", [(1366, 768), (1366, 700)])  # the screen, and the screen minus a taskbar
def test_every_control_of_a_run_is_on_screen(qtbot, tmp_path, size):
    win = make_window(qtbot, tmp_path, size=size)
    assert (win.width(), win.height()) == size
    rc = win.run_controls
    for name, b in rc.buttons.items():
        assert _fully_visible(b, win), name
    assert _fully_visible(rc.phase_label, win) and _fully_visible(rc.detail_label, win)
    assert _fully_visible(win.phase_label, win)  # the status bar's phase
    # the plot is on screen too, and the window asks for no more than the laptop has
    assert _fully_visible(win.live.strip, win)
    hint = win.minimumSizeHint()
    assert hint.width() <= size[0] and hint.height() <= size[1]


def test_value_fields_ignore_the_wheel_unless_focused(qtbot, tmp_path):
    from PySide6.QtCore import QPoint, QPointF, Qt
    from PySide6.QtGui import QWheelEvent
    from PySide6.QtWidgets import QAbstractSpinBox, QApplication, QComboBox

    win = make_window(qtbot, tmp_path)
    rp = win.run_panel
    win.run_page.scroll.ensureWidgetVisible(rp.beta_spin)
    qtbot.wait(50)

    def wheel(w, steps=1):
        pos = QPointF(w.rect().center())
        ev = QWheelEvent(pos, QPointF(w.mapToGlobal(pos.toPoint())), QPoint(0, 0), QPoint(0, 120 * steps),
                         Qt.NoButton, Qt.NoModifier, Qt.NoScrollPhase, False)
        QApplication.sendEvent(w, ev)

    rp.title_edit.setFocus()
    qtbot.waitUntil(lambda: rp.title_edit.hasFocus(), timeout=2000)
    beta = rp.beta_spin.value()
    rate = rp.rate_combo.currentIndex()
    for _ in range(3):
        wheel(rp.beta_spin)
        wheel(rp.rate_combo, -1)
    assert rp.beta_spin.value() == beta and rp.rate_combo.currentIndex() == rate  # the manoeuvre is unchanged
    assert not rp.beta_spin.hasFocus()  # and the wheel did not take the focus
    rp.beta_spin.setFocus()
    qtbot.waitUntil(lambda: rp.beta_spin.hasFocus(), timeout=2000)
    wheel(rp.beta_spin)
    assert rp.beta_spin.value() == pytest.approx(beta + rp.beta_spin.singleStep())  # focused: it is a control
    # every value field of the window (run form, archive) behaves so
    fields = win.findChildren(QAbstractSpinBox) + win.findChildren(QComboBox)
    assert fields and all(f.focusPolicy() == Qt.StrongFocus for f in fields)


def test_fit_table_shows_every_model_and_j_tau_labels_do_not_overlap(qtbot, tmp_path, sweep):
    from PySide6.QtGui import QPainter, QPicture

    t, h, rig, result = sweep
    win = make_window(qtbot, tmp_path)
    fp = win.fit_panel
    win.tabs.setCurrentWidget(fp)
    fp.set_fit(t, h, rig, result, title="layout test")
    qtbot.waitUntil(lambda: fp.data is not None, timeout=30000)
    qtbot.wait(100)
    names = fp.model_names()
    assert names == ["EL", "S1", "S2", "S3", "S4", "S5", "S6", "S1r", "S2r", "S3r", "S4r", "S5r"]
    table = fp.table
    assert table.verticalScrollBar().maximum() == 0
    viewport = table.viewport().rect()
    for r in range(table.rowCount()):
        assert viewport.contains(table.visualRect(table.model().index(r, 1))), names[r]
    assert _fully_visible(table.viewport(), win) and _fully_visible(fp.plots.viewport(), win)
    # the tick labels of the log axes of the J-tau and |phi| plots: no two overlap
    for plot in (fp.p_creep, fp.p_phi):
        for side in ("left", "bottom"):
            ax = plot.getAxis(side)
            pic = QPicture()
            painter = QPainter(pic)
            specs = ax.generateDrawSpecs(painter)
            painter.end()
            rects = [(rect, text) for rect, _, text in specs[2] if text]
            assert len(rects) >= 2, (side, rects)
            for i, (a, ta) in enumerate(rects):
                for b, tb in rects[i + 1:]:
                    assert not a.intersects(b), (side, ta, tb)


def test_the_creep_plot_shows_the_model_averaged_band_where_the_choice_is_uncertain(qtbot, tmp_path, sweep):
    from velab.fitting.results import SweepResult
    from velab.gui.fit_panel import AVERAGED_LABEL

    t, h, rig, result = sweep
    win = make_window(qtbot, tmp_path)
    fp = win.fit_panel
    win.tabs.setCurrentWidget(fp)

    def labels():
        return [item.name() for item in fp.p_creep.listDataItems() if item.name()]

    sure = SweepResult.from_dict(result.to_dict())
    for f in sure.models:  # the best model holds all the weight: its own band only
        f.weight = 1.0 if f is sure.best else 0.0
    fp.set_fit(t, h, rig, sure, title="one model")
    qtbot.waitUntil(lambda: fp.data is not None and fp.data.get("result") is sure, timeout=30000)
    qtbot.waitUntil(lambda: sure.best.name in labels(), timeout=10000)
    assert AVERAGED_LABEL not in labels() and fp.data["creep_averaged"] is None
    torn = SweepResult.from_dict(result.to_dict())
    other = next(f for f in torn.models if f.m and f is not torn.best and not f.equivalent_to and not f.reduced)
    for f in torn.models:  # two models share it
        f.weight = 0.6 if f is torn.best else 0.4 if f is other else 0.0
    fp.set_fit(t, h, rig, torn, title="two models")
    qtbot.waitUntil(lambda: fp.data is not None and fp.data.get("result") is torn, timeout=30000)
    qtbot.waitUntil(lambda: AVERAGED_LABEL in labels(), timeout=10000)
    avg = torn.creep_averaged()
    assert avg.weights[torn.best.name] == pytest.approx(0.6) and avg.weights[other.name] == pytest.approx(0.4)


def test_fit_table_reports_bounds_negligible_elements_and_uncertainties(sweep):
    """The fitter's findings are read from the result's to_dict() when present (the fitter's
    `at_bounds`, `note`, per-element `negligible` and standard errors), absent ones leave cells empty."""
    from velab.gui.fit_rows import COLUMNS, model_rows

    *_, result = sweep
    plain = {r.name: r for r in model_rows(result)}
    assert plain["S3"].cells[COLUMNS.index("notes")] == "" or result.to_dict()["models"][3].get("at_bounds")
    assert plain[result.best.name].best
    doc = copy.deepcopy(result.to_dict())
    s2 = next(m for m in doc["models"] if m["name"] == "S2")
    s2["wave_speed_se"] = 0.42
    s2["note"] = "S2 = S1 + negligible element"
    s2["at_bounds"] = [{"parameter": "tau_2", "bound": "upper", "limit": 30.0, "option": "--tau-max"}]
    s2["elements"][1].update(negligible=True, J_rel=1e-5)
    s2["elements"][0].update(tau_se=0.003, J_se=1e-12)
    doc["selection"] = "ar1"
    for m in doc["models"]:
        m["aic_ar1"] = m["aic"] - 5.0
    rows = {r.name: r for r in model_rows(doc)}
    r = rows["S2"]
    assert r.cells[COLUMNS.index("a (m/s)")].endswith("± 0.42")
    notes = r.cells[COLUMNS.index("notes")]
    assert "S2 = S1 + negligible element" in notes and "tau_2 on the upper bound 30 s (--tau-max moves it)" in notes
    assert r.negligible == (False, True) and "element 2: negligible" in r.tooltip and "±" in r.tooltip
    assert rows["S3"].cells[COLUMNS.index("AIC")] == f"{s2 and doc['models'][3]['aic_ar1']:.1f}"
    assert np.isfinite(float(rows["EL"].cells[COLUMNS.index("F (m²)")]))


def test_whole_run_view_and_zoom(qtbot, tmp_path):
    """After a run the live plot shows the whole run on the strip chart; a click opens the zoomable view."""
    from PySide6.QtCore import Qt

    win = make_window(qtbot, tmp_path)
    live = win.live
    t = np.arange(-2.0, 5.0, 1e-3)
    live.append(t, 35 + 10 * np.sin(3 * t) * (t > 0), np.where(t > 0.1, 0.0, 100.0))
    live.set_trigger(0.1, measured=True)
    live.show_whole()
    assert live.stack.currentWidget() is live.strip and live.strip.zoomable
    assert live.strip.x_range == pytest.approx((-2.1, t[-1] - 0.1))
    qtbot.mouseClick(live.strip, Qt.LeftButton)
    assert live.stack.currentWidget() is live.view
    x, _ = live.head_curve.getData()
    assert x.size == t.size and x[0] == pytest.approx(-2.1)
