"""Real screenshots of the operator window on an X server (Xvfb), and what each shows, for the tests.

Run under ``xvfb-run`` (tests/gui/test_gui_screens.py does it):

    xvfb-run -a -s "-screen 0 1366x768x24" python tests/gui/xvfb_shots.py run --out DIR
    xvfb-run -a -s "-screen 0 1366x768x24" python tests/gui/xvfb_shots.py archive --out DIR

``run``: the window on the real engine and the in-process simulated rig (a scaled clock), the controls
pressed as an operator does, one shot per phase: ``connected``, ``armed``, ``recording``, ``fitting``,
``fitted`` (the Fit page after the final fit), ``ended`` (the Run page after it) and ``refused`` (a surge
margin the interlock refuses); with ``--quick`` only ``connected`` and ``refused``. ``archive``: the Archive tab with 1,000 catalogued runs (rows of a real
synthetic run file, one every 7 s of one day) and one run opened below the table.

Each shot is the X server's whole screen (``QScreen.grabWindow(0)``: what is on the display, not a
widget's own rendering) saved as DIR/NAME.png, and DIR/NAME.json says, for every essential widget, where
it is on the screen, whether it is inside the window and the screen and not clipped by a scroll area or
a parent, whether its text fits (not elided, not cut), whether it is enabled, and the phase shown. The
window is the screen's size (no window manager: at 0, 0, without a frame). Exit 0 when every shot was
taken; 1 and a line on stderr otherwise.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

os.environ["QT_QPA_PLATFORM"] = "xcb"  # the real display, whatever the test process uses
HERE = Path(__file__).resolve().parent


def _fits_text(w) -> bool:
    """The widget's text is drawn whole: not elided, not cut by its own size."""
    from PySide6.QtWidgets import QAbstractButton, QCheckBox, QLabel, QLineEdit

    fm = w.fontMetrics()
    if isinstance(w, QLabel):
        cr = w.contentsRect()
        if w.wordWrap() or w.textFormat() == 1:  # Qt.RichText or wrapped: the height the width needs
            return w.heightForWidth(cr.width() + 2 * w.margin()) <= w.height() + 1 if w.wordWrap() else \
                w.sizeHint().width() <= w.width() + 1
        lines = w.text().splitlines() or [""]
        return (max(fm.horizontalAdvance(s) for s in lines) <= cr.width() + 1
                and fm.lineSpacing() * len(lines) <= cr.height() + 2)
    if isinstance(w, QCheckBox):
        return w.sizeHint().width() <= w.width() + 1
    if isinstance(w, QAbstractButton):
        return fm.horizontalAdvance(w.text()) + 8 <= w.width()
    if isinstance(w, QLineEdit):
        return fm.horizontalAdvance(w.text() or w.placeholderText()) + 8 <= w.width()
    return True


def _unclipped(w) -> bool:
    """No ancestor (a scroll area's viewport, a splitter) cuts the widget: its rectangle is inside each
    ancestor's, in window coordinates (visibleRegion also drops what siblings overlap, e.g. a graphics
    view's own viewport)."""
    from PySide6.QtCore import QPoint, QRect

    win = w.window()
    r = QRect(w.mapTo(win, QPoint(0, 0)), w.size())
    p = w.parentWidget()
    while p is not None and p is not win:
        if not QRect(p.mapTo(win, QPoint(0, 0)), p.size()).contains(r):
            return False
        p = p.parentWidget()
    return True


def describe(win, name: str, w) -> dict:
    """Where ``w`` is on the screen and whether all of it can be seen."""
    from PySide6.QtCore import QPoint, QRect

    g = QRect(w.mapToGlobal(QPoint(0, 0)), w.size())
    screen = win.screen().geometry()
    frame = win.frameGeometry()
    text = w.text() if hasattr(w, "text") and callable(w.text) else ""
    return {
        "name": name, "rect": [g.x(), g.y(), g.width(), g.height()], "text": text,
        "visible": bool(w.isVisible()),
        "unclipped": bool(w.isVisible() and _unclipped(w)),
        "in_window": bool(frame.contains(g)), "on_screen": bool(screen.contains(g)),
        "text_fits": bool(_fits_text(w)), "enabled": bool(w.isEnabled()),
    }


def table_facts(view) -> dict:
    """Rows fully on screen in a QTableView, and each column's widest shown text against its width."""
    model = view.model()
    vp = view.viewport()
    rows = [r for r in range(model.rowCount())
            if view.rowViewportPosition(r) >= 0
            and view.rowViewportPosition(r) + view.rowHeight(r) <= vp.height()]
    fm = view.fontMetrics()
    cut = []
    for c in range(model.columnCount()):
        width = view.columnWidth(c)
        if view.isColumnHidden(c) or view.horizontalHeader().stretchLastSection() and c == model.columnCount() - 1:
            continue
        for r in rows:
            s = str(model.data(model.index(r, c)) or "")
            if fm.horizontalAdvance(s) + 6 > width:
                cut.append([c, r, s, width])
                break
    return {"rows_visible": len(rows), "rows": model.rowCount(), "cut_cells": cut,
            "texts": [[str(model.data(model.index(r, c)) or "") for c in range(model.columnCount())] for r in rows]}


class Shots:
    def __init__(self, win, out: Path):
        self.win, self.out = win, out
        out.mkdir(parents=True, exist_ok=True)

    def take(self, name: str, widgets: dict, extra: dict | None = None) -> None:
        from PySide6.QtGui import QGuiApplication

        from velab.gui.eventloop import wait_until

        # the buttons' state at the moment the caller saw the phase (``extra`` was read then, in this event-loop
        # turn): the phase can move on while the paint settles (a final fit that ends within it)
        controls = {k: bool(v.isEnabled()) for k, v in widgets.items() if k.startswith("button:")}
        wait_until(lambda: False, 0.25)  # the last layout and paint are on the screen
        screen = QGuiApplication.primaryScreen()
        screen.grabWindow(0).save(str(self.out / f"{name}.png"))
        w = self.win
        g = w.frameGeometry()
        doc = {"name": name, "screen": [screen.geometry().width(), screen.geometry().height()],
               "window": [g.x(), g.y(), g.width(), g.height()],
               "widgets": [describe(w, k, v) for k, v in widgets.items()], "controls_at_phase": controls,
               **(extra or {})}
        (self.out / f"{name}.json").write_text(json.dumps(doc, indent=1))


def run_page_widgets(win) -> dict:
    rc = win.run_controls
    d = {f"button:{n}": b for n, b in rc.buttons.items()}
    d.update({"phase": rc.phase_label, "phase detail": rc.detail_label, "status phase": win.phase_label,
              "interlock": win.run_page.interlock, "devices table": win.devices.table,
              "messages": win.messages_dock})
    return d


def scenario_run(out: Path, clock: str, quick: bool = False) -> int:
    from velab.configpath import DEFAULT_SIM
    from velab.gui.app import ensure_app, recorder_factory
    from velab.gui.eventloop import wait_until
    from velab.gui.main_window import MainWindow, make_settings

    ensure_app()
    tmp = Path(tempfile.mkdtemp(prefix="velab-xvfb-"))
    factory, rig = recorder_factory(simulate=True, clock=clock, material="A")
    win = MainWindow(settings=make_settings(tmp / "gui.ini"), recorder_factory=factory, rig=rig,
                     source_label=f"simulated bench '{DEFAULT_SIM}', material A")
    rp, rc = win.run_panel, win.run_controls
    rp.title_edit.setText("closure 3, material A")
    rp.operator_edit.setText("M. Rossi")
    rp.duration_spin.setValue(5.0)
    rp.pre_spin.setValue(4.5)  # 1.5 s of the armed phase at the 3x clock: time for its shot
    # a final fit that lasts long enough to be seen on the screen (EL..S6 on 4 s): with EL, S1 on 1.5 s it could end
    # within one of the window's phase updates on a quiet host, and EL..S3 on 3 s (the one engine's faster fit)
    # within the shot's 0.25 s paint wait, which then showed the run completed under a "fitting" record
    rp.fit_window_spin.setValue(4.0)
    rp.models_edit.setText("0-6")
    rp.rate_combo.setCurrentIndex(rp.rate_combo.findData(1000.0))
    rp.out_edit.setText(str(tmp / "runs"))
    screen = win.screen().geometry()
    win.resize(screen.width(), screen.height())
    win.show()
    wait_until(lambda: win.isVisible() and win.windowHandle() is not None and win.windowHandle().isExposed(), 10)
    shots = Shots(win, out)
    log = lambda: " | ".join(win.log.texts()[-6:])  # noqa: E731

    def phase_shown() -> str:
        return rc.phase_label.text()

    def step(cond, timeout, what) -> None:
        if not wait_until(cond, timeout):
            raise SystemExit(f"{what}: phase {phase_shown()!r}, log {log()}")

    def extra() -> dict:
        return {"phase": phase_shown(), "detail": rc.detail_label.text(), "engine_phase": win.controller.phase,
                "devices": table_facts(win.devices.table), "log": win.log.texts()[-8:]}

    step(lambda: rc.buttons["connect"].isEnabled(), 60, "Connect never enabled")
    rc.buttons["connect"].click()
    step(lambda: win.controller.phase == "ready" and win.devices.value("head") is not None, 60,
         "no steady head after Connect")
    shots.take("connected", run_page_widgets(win), extra())
    if quick:  # the window's layout alone: connected, and the interlock refusing
        rp.margin_spin.setValue(400)
        step(lambda: not rc.buttons["arm"].isEnabled(), 10, "Arm stayed enabled under a refusing interlock")
        shots.take("refused", run_page_widgets(win), extra())
        win.close()
        return 0
    rc.buttons["arm"].click()
    step(lambda: win.controller.phase == "armed", 60, "never armed")
    shots.take("armed", run_page_widgets(win), extra())
    step(lambda: rc.buttons["trigger"].isEnabled(), 60, "Trigger never enabled")
    rc.buttons["trigger"].click()
    step(lambda: win.controller.phase == "recording" and win.live.trigger_measured, 60, "never recording")
    shots.take("recording", run_page_widgets(win), extra())
    step(lambda: phase_shown() == "fitting" or win.last_summary is not None, 120, "the fitting phase never shown")
    shots.take("fitting", run_page_widgets(win), extra())
    step(lambda: win.last_summary is not None, 180, "the run did not end")
    if win.last_summary.fit is None:
        raise SystemExit(f"the run ended without its final fit: {win.last_summary.fit_error or log()}")
    step(lambda: win.fit_panel.result is not None and "final fit" in win.fit_panel.title, 60,
         "the final fit never reached the Fit page")
    step(lambda: win.controller.phase not in ("fitting", "recording"), 60, "the run did not end")
    shots.take("ended", run_page_widgets(win), extra())
    win.tabs.setCurrentWidget(win.fit_panel)
    step(lambda: win.fit_panel.data is not None, 120, "the fit panel never drew")
    fp = win.fit_panel
    shots.take("fitted", {"fit header": fp.header, "fit summary": fp.summary, "fit table": fp.table,
                          "fit plots": fp.plots, "messages": win.messages_dock},
               {**extra(), "summary_text": fp.summary.text(), "status": win.last_summary.status})
    win.tabs.setCurrentWidget(win.run_page)
    rp.margin_spin.setValue(400)  # the interlock refuses a 5x Joukowsky surge on this rig
    step(lambda: not rc.buttons["arm"].isEnabled(), 10, "Arm stayed enabled under a refusing interlock")
    shots.take("refused", run_page_widgets(win), extra())
    win.close()
    return 0


def archive_rows(n: int, tmp: Path) -> list[dict]:
    """n catalogue rows: a real synthetic run's row, one every 7 s of one day, titled apart."""
    import datetime as dt

    from velab.catalogue.rows import read_row
    from velab.cli import main as velab_main

    path = tmp / "a.h5"
    assert velab_main(["synth", "--material", "A", "--duration", "3", "-q", "-o", str(path)]) == 0
    base = read_row(str(path))
    t0 = dt.datetime(2026, 11, 21, 8, 0, 0, tzinfo=dt.timezone.utc)
    rows = []
    for i in range(n):
        r = dict(base)
        r["path"] = str(tmp / f"day0/run{i:04d}.h5")
        r["start_time"] = (t0 + dt.timedelta(seconds=7 * i)).isoformat()
        r["title"] = f"closure {i}"
        rows.append(r)
    return rows, path


def scenario_archive(out: Path) -> int:
    from velab.gui.app import ensure_app
    from velab.gui.eventloop import wait_until
    from velab.gui.main_window import MainWindow, make_settings

    ensure_app()
    tmp = Path(tempfile.mkdtemp(prefix="velab-xvfb-"))
    rows, path = archive_rows(1000, tmp)
    win = MainWindow(settings=make_settings(tmp / "gui.ini"))
    screen = win.screen().geometry()
    win.resize(screen.width(), screen.height())
    arch = win.archive
    win.tabs.setCurrentWidget(arch)
    win.show()
    wait_until(lambda: win.windowHandle() is not None and win.windowHandle().isExposed(), 10)
    arch.catalogue.model.set_rows(rows)
    arch.catalogue.show_count()
    arch.open(path)
    if not wait_until(lambda: arch.run.loaded_run is not None, 60):
        raise SystemExit(f"the run did not open: {win.log.texts()}")
    arch.catalogue.best_filter.setText("S9")
    arch.catalogue.apply_filters()
    wait_until(lambda: False, 0.1)
    shots = Shots(win, out)
    controls = {"open": arch.run.open_button, "folder": arch.run.folder_button, "reload": arch.run.reload_button,
                "follow": arch.run.follow, "refit": arch.fits.refit_button, "export figure": arch.run.export_fig_button,
                "export csv": arch.run.export_csv_button, "rescan": arch.catalogue.rescan_button, "index label": arch.catalogue.index_label,
                "open selected": arch.catalogue.open_selected_button, "refit selected": arch.catalogue.refit_selected_button,
                "fit together": arch.catalogue.joint_fit_button, "export rows": arch.catalogue.export_rows_button,
                "trends": arch.catalogue.trends_button, "best filter": arch.catalogue.best_filter, "table": arch.catalogue.table}
    shots.take("archive-bad-filter", controls, {"table": table_facts(arch.catalogue.table),
                                                "best_filter_tip": arch.catalogue.best_filter.toolTip(),
                                                "best_filter_style": arch.catalogue.best_filter.styleSheet()})
    arch.catalogue.best_filter.setText("")
    arch.catalogue.apply_filters()
    shots.take("archive", controls, {"table": table_facts(arch.catalogue.table)})
    win.close()
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario", choices=("run", "archive"))
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--clock", default="scaled:3")
    ap.add_argument("--quick", action="store_true", help="run: only the connected and refused shots (no run)")
    args = ap.parse_args(argv)
    if args.scenario == "run":
        return scenario_run(args.out, args.clock, args.quick)
    return scenario_archive(args.out)


if __name__ == "__main__":
    sys.exit(main())
