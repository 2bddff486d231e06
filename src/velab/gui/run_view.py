"""The Archive tab's run view: one run (also one still being written: SWMR), its metadata and data, its
stored fits, a re-fit's result, and the exports of the report figure and of its samples as CSV. Files
are read and written on the GUI's thread pool (velab.gui.tasks), never on the GUI thread.

Its widgets: ``file_bar`` (Open run…, Folder…, Reload, Follow, the stored fits), ``export_bar``
(Figure…, CSV…) and ``tabs`` (Run, Fit, Trends), placed by the Archive tab (velab.gui.archive).
Signals: ``message(text, level)``, ``loaded(path)`` once a run and its fits are shown (``run_loaded``
with the LoadedRun), ``folder_requested()`` (Folder…), ``exported(path)``.
"""

from __future__ import annotations

from pathlib import Path

from PySide6.QtCore import QObject, QSettings, QTimer, Qt, Signal
from PySide6.QtGui import QFont
from PySide6.QtWidgets import (QCheckBox, QFileDialog, QHBoxLayout, QLabel, QPlainTextEdit, QPushButton, QScrollArea,
                               QSplitter, QTabWidget, QVBoxLayout, QWidget)

from velab.gui import tasks
from velab.gui.archive_io import export_csv, export_report_figure, load_run
from velab.gui.fit_panel import FitPanel
from velab.gui.live_plot import LivePlot
from velab.gui.messages import describe_error
from velab.gui.trends import TrendsView
from velab.gui.widgets import ComboBox


class RunView(QObject):
    message = Signal(str, str)
    loaded = Signal(str)
    run_loaded = Signal(object)
    folder_requested = Signal()
    exported = Signal(str)

    def __init__(self, settings: QSettings, parent=None):
        super().__init__(parent)
        self.settings = settings
        self.path: Path | None = None
        self.loaded_run = None
        self.current_fit = None  # (name, SweepResult)
        self.busy = False  # a fit runs (the fit controller's): a run being written is not re-read meanwhile
        self._loading = False
        self._build_file_bar()
        self._build_export_bar()
        self._build_tabs()
        self.follow_timer = QTimer(self)
        self.follow_timer.setInterval(2000)
        self.follow_timer.timeout.connect(self._follow_tick)
        self.follow_timer.start()
        self._update_buttons()

    # ------------------------------------------------------------------ widgets
    def _build_file_bar(self) -> None:
        self.file_bar = bar = QWidget()
        lay = QVBoxLayout(bar)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.setSpacing(3)
        row = QHBoxLayout()
        self.open_button = QPushButton("Open run…")
        self.open_button.clicked.connect(self.choose_file)
        self.folder_button = QPushButton("Folder…")
        self.folder_button.clicked.connect(self.folder_requested.emit)
        self.reload_button = QPushButton("Reload")
        self.reload_button.setToolTip("read the run again (a run being recorded grows)")
        self.reload_button.clicked.connect(self.reload)
        for b in (self.open_button, self.folder_button, self.reload_button):
            row.addWidget(b)
        lay.addLayout(row)
        self.follow = QCheckBox("Follow a run being written")
        self.follow.setToolTip("a run still being recorded is re-read every 2 s (SWMR)")
        self.follow.setChecked(True)
        lay.addWidget(self.follow)
        fits_row = QHBoxLayout()
        fits_row.addWidget(QLabel("stored fit"))
        self.fit_combo = ComboBox()
        self.fit_combo.currentIndexChanged.connect(self._fit_chosen)
        fits_row.addWidget(self.fit_combo, 1)
        lay.addLayout(fits_row)

    def _build_export_bar(self) -> None:
        self.export_bar = bar = QWidget()
        el = QHBoxLayout(bar)
        el.setContentsMargins(0, 0, 0, 0)
        el.addWidget(QLabel("export"))
        self.export_fig_button = QPushButton("Figure…")
        self.export_fig_button.setToolTip("the report figure of the shown fit (.png, .pdf, .svg)")
        self.export_fig_button.clicked.connect(lambda: self.export_figure())
        self.export_csv_button = QPushButton("CSV…")
        self.export_csv_button.setToolTip("the run's samples as CSV")
        self.export_csv_button.clicked.connect(lambda: self.export_csv())
        el.addWidget(self.export_fig_button)
        el.addWidget(self.export_csv_button)

    def _build_tabs(self) -> None:
        self.tabs = QTabWidget()
        run_page = QSplitter(Qt.Vertical)
        self.summary = QPlainTextEdit()
        self.summary.setReadOnly(True)
        mono = QFont("Monospace")
        mono.setStyleHint(QFont.TypeWriter)
        mono.setPointSize(9)
        self.summary.setFont(mono)
        self.summary.setPlaceholderText("Open a run file (.h5) to see its metadata, data and fits.")
        run_page.addWidget(self.summary)
        self.run_plot = LivePlot()
        run_page.addWidget(self.run_plot)
        run_page.setStretchFactor(0, 1)
        run_page.setStretchFactor(1, 2)
        # small minimums: under ten catalogue rows at 1366 x 768 the run's view has ~270 px
        self.summary.setMinimumHeight(48)
        self.run_plot.setMinimumHeight(150)
        self.tabs.addTab(run_page, "Run")
        self.fit_panel = FitPanel(title="No fit shown")
        # in a scroll area: the panel (every model row, the plots) is taller than the room left under ten
        # catalogue rows at 1366 x 768; without one it would push the catalogue down to a few rows
        self.fit_scroll = QScrollArea()
        self.fit_scroll.setWidgetResizable(True)
        self.fit_panel.setMinimumHeight(460)
        self.fit_scroll.setWidget(self.fit_panel)
        self.tabs.addTab(self.fit_scroll, "Fit")
        self.trends = TrendsView()
        self.tabs.addTab(self.trends, "Trends")

    # ------------------------------------------------------------------ the run
    def choose_file(self) -> None:
        start = str(self.settings.value("archive/folder", "") or Path.cwd())
        path, _ = QFileDialog.getOpenFileName(self.file_bar, "Open a run", start,
                                              "Run files (*.h5 *.hdf5 *.nxs);;All files (*)")
        if path:
            self.open(path)

    def open(self, path) -> None:
        """Read the run and its fits on a worker thread, then show them."""
        self.path = Path(path)
        self.settings.setValue("archive/last_run", str(self.path))
        self.message.emit(f"Opening {self.path.name}…", "info")
        self._load(select=None)

    def reload(self) -> None:
        if self.path is not None:
            self._load(select=self.fit_combo.currentText() or None, quiet=True)

    def _load(self, select=None, quiet: bool = False) -> None:
        if self._loading:
            return
        self._loading = True
        path = self.path
        tasks.submit(load_run, path, owner=self, on_done=lambda lr: self._loaded(lr, path, select, quiet),
                     on_error=self._load_failed)

    def _load_failed(self, exc) -> None:
        self._loading = False
        level, text = describe_error(exc)
        self.message.emit(text, level)

    def _loaded(self, lr, path, select, quiet) -> None:
        self._loading = False
        if path != self.path:
            return
        self.loaded_run = lr
        run = lr.run
        self.summary.setPlainText(lr.summary)
        valve = run.channels.get("valve_position")
        self.run_plot.set_run(run.time_s, run.head_m, valve, run.trigger_time_s)
        self.run_plot.head_plot.setTitle(f"{path.name}: {run.title}" if run.title else path.name)
        self.fit_combo.blockSignals(True)
        self.fit_combo.clear()
        self.fit_combo.addItems(list(lr.fits))
        self.fit_combo.blockSignals(False)
        self.run_loaded.emit(lr)
        if lr.fits:
            name = select if select in lr.fits else list(lr.fits)[-1]
            self.fit_combo.setCurrentText(name)
            self._show_fit(name)
        else:
            self.current_fit = None
            self.fit_panel.clear("No fit stored in this run: use Re-fit.")
        for name, err in lr.fit_errors.items():
            self.message.emit(f"{path.name}: fit {name} unreadable: {err}", "warning")
        if not quiet:
            state = "still being written (or never closed)" if run.incomplete else run.status
            self.message.emit(f"Opened {path.name}: {run.n_samples} samples at {run.sample_rate_hz:g} Hz, "
                              f"{state}, {len(lr.fits)} fit(s)", "info")
        self._update_buttons()
        self.loaded.emit(str(path))

    def _follow_tick(self) -> None:
        lr = self.loaded_run
        if (self.follow.isChecked() and lr is not None and lr.run.incomplete and not self.busy
                and self.tabs.isVisible()):
            self.reload()

    # ------------------------------------------------------------------ fits
    def _fit_chosen(self, _index) -> None:
        name = self.fit_combo.currentText()
        if name and self.loaded_run is not None and name in self.loaded_run.fits:
            self._show_fit(name)

    def _show_fit(self, name) -> None:
        lr = self.loaded_run
        result = lr.fits[name]
        self.current_fit = (name, result)
        run = lr.run
        try:
            window = min(result.window_s, run.duration_after_trigger_s)
            t, h = run.fit_window(window)
        except Exception as exc:
            self.message.emit(f"fit {name}: cannot cut its window from the run: {describe_error(exc)[1]}", "warning")
            return
        self.fit_panel.set_fit(t, h, run.rig, result, title=f"{self.path.name} — stored fit {name}")

    def show_refit(self, path, out) -> None:
        """A re-fit's outcome (velab.gui.archive_io.RefitOutcome) of the run at ``path``: shown if it is this
        run's, and listed with its stored fits once saved."""
        r = out.result
        name = out.saved_as or "(unsaved)"
        self.current_fit = (name, r)
        if path == self.path:
            self.fit_panel.set_fit(out.t, out.h, out.rig, r, title=f"{path.name} — re-fit {name}")
            self.tabs.setCurrentWidget(self.fit_scroll)
        if out.saved_as and self.loaded_run is not None and path == self.path:
            self.loaded_run.fits[out.saved_as] = r
            self.fit_combo.blockSignals(True)
            if self.fit_combo.findText(out.saved_as) < 0:
                self.fit_combo.addItem(out.saved_as)
            self.fit_combo.setCurrentText(out.saved_as)
            self.fit_combo.blockSignals(False)
        self._update_buttons()

    # ------------------------------------------------------------------ export
    def export_figure(self, path=None) -> None:
        if self.current_fit is None or self.path is None:
            self.message.emit("No fit to export: open a run with a fit, or re-fit it first.", "warning")
            return
        if path is None:
            start = str(self.path.with_name(self.path.stem + "_fit.png"))
            path, _ = QFileDialog.getSaveFileName(self.tabs, "Export the report figure", start,
                                                  "PNG (*.png);;PDF (*.pdf);;SVG (*.svg)")
            if not path:
                return
        tasks.submit(export_report_figure, self.path, self.current_fit[1],
                     path, owner=self, on_done=self._exported, on_error=self._export_failed)

    def export_csv(self, path=None) -> None:
        if self.loaded_run is None:
            self.message.emit("No run to export: open one first.", "warning")
            return
        if path is None:
            start = str(self.path.with_suffix(".csv"))
            path, _ = QFileDialog.getSaveFileName(self.tabs, "Export the run as CSV", start, "CSV (*.csv)")
            if not path:
                return
        tasks.submit(export_csv, self.loaded_run.run, path, owner=self, on_done=self._exported,
                     on_error=self._export_failed)

    def _exported(self, path) -> None:
        self.message.emit(f"Exported {path}", "info")
        self.exported.emit(str(path))

    def _export_failed(self, exc) -> None:
        level, text = describe_error(exc)
        self.message.emit(f"Export failed: {text}", level)

    def _update_buttons(self) -> None:
        self.reload_button.setEnabled(self.path is not None)
        self.export_csv_button.setEnabled(self.loaded_run is not None)
        self.export_fig_button.setEnabled(self.current_fit is not None or self.loaded_run is not None)
