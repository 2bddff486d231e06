"""The archive browser: open earlier runs (also one still being written), see metadata and fits,
re-fit with other settings in the background, export the report figure and a CSV."""

from __future__ import annotations

from pathlib import Path

from PySide6.QtCore import QSettings, Qt, QTimer, Signal
from PySide6.QtGui import QFont
from PySide6.QtWidgets import (QCheckBox, QFileDialog, QFormLayout, QGroupBox,
                               QHBoxLayout, QLabel, QLineEdit, QListWidget, QListWidgetItem, QPlainTextEdit,
                               QProgressBar, QPushButton, QScrollArea, QSplitter, QTabWidget, QVBoxLayout,
                               QWidget)

from velab.gui import tasks
from velab.gui.archive_io import RefitOptions, export_csv, export_report_figure, list_runs, load_run, refit
from velab.gui.fit_panel import FitPanel
from velab.gui.live_plot import LivePlot
from velab.gui.messages import describe_error
from velab.gui.widgets import ComboBox, DoubleSpinBox, SpinBox


class ArchiveBrowser(QWidget):
    """Signals ``message(text, level)`` for the window's message log and banner."""

    message = Signal(str, str)
    loaded = Signal(str)  # path, once a run and its fits are shown
    refitted = Signal(str)  # best model of a finished re-fit
    exported = Signal(str)  # path of an exported file

    def __init__(self, settings: QSettings, parent=None):
        super().__init__(parent)
        self.settings = settings
        self.path: Path | None = None
        self.loaded_run = None
        self.current_fit = None  # (name, SweepResult)
        self.busy = False
        self._loading = False

        outer = QHBoxLayout(self)
        outer.setContentsMargins(2, 2, 2, 2)
        split = QSplitter(Qt.Horizontal)
        self.splitter = split
        outer.addWidget(split)

        # ------------------------------------------------------------ left column
        left = QWidget()
        ll = QVBoxLayout(left)
        ll.setContentsMargins(2, 2, 2, 2)
        row = QHBoxLayout()
        self.open_button = QPushButton("Open run…")
        self.open_button.clicked.connect(self.choose_file)
        self.folder_button = QPushButton("Folder…")
        self.folder_button.clicked.connect(self.choose_folder)
        self.reload_button = QPushButton("Reload")
        self.reload_button.setToolTip("read the run again (a run being recorded grows)")
        self.reload_button.clicked.connect(self.reload)
        for b in (self.open_button, self.folder_button, self.reload_button):
            row.addWidget(b)
        ll.addLayout(row)
        self.follow = QCheckBox("Follow a run being written (re-read every 2 s)")
        self.follow.setChecked(True)
        ll.addWidget(self.follow)
        self.folder_label = QLabel()
        self.folder_label.setWordWrap(True)
        ll.addWidget(self.folder_label)
        self.files = QListWidget()
        self.files.itemActivated.connect(lambda it: self.open(it.data(Qt.UserRole)))
        self.files.itemClicked.connect(lambda it: self.open(it.data(Qt.UserRole)))
        ll.addWidget(self.files, 1)

        fits_box = QGroupBox("Stored fits")
        fl = QVBoxLayout(fits_box)
        self.fit_combo = ComboBox()
        self.fit_combo.currentIndexChanged.connect(self._fit_chosen)
        fl.addWidget(self.fit_combo)
        ll.addWidget(fits_box)

        refit_box = QGroupBox("Re-fit")
        form = QFormLayout(refit_box)
        self.models_edit = QLineEdit(settings.value("archive/models", "0-6"))
        self.models_edit.setToolTip("models by number of Kelvin-Voigt elements: 0-6, 1-4, 1,3 (0 = EL)")
        self.window_spin = DoubleSpinBox()
        self.window_spin.setRange(0.1, 3600)
        self.window_spin.setDecimals(2)
        self.window_spin.setSuffix(" s")
        self.window_spin.setValue(float(settings.value("archive/window_s", 20.0)))
        self.method_combo = ComboBox()
        from velab.fitting import METHODS

        self.method_combo.addItems(METHODS)
        self.method_combo.setCurrentText(settings.value("archive/method", "auto"))
        self.starts_spin = SpinBox()
        self.starts_spin.setRange(0, 50)
        self.starts_spin.setSpecialValueText("all")
        self.starts_spin.setToolTip("cap on the number of starts per model (all: the full search)")
        self.reduced_check = QCheckBox("also reduced S1r..S5r")
        self.save_check = QCheckBox("store the fit in the run file")
        self.save_check.setChecked(True)
        form.addRow("models", self.models_edit)
        form.addRow("window", self.window_spin)
        form.addRow("method", self.method_combo)
        form.addRow("starts", self.starts_spin)
        form.addRow(self.reduced_check)
        form.addRow(self.save_check)
        self.refit_button = QPushButton("Re-fit")
        self.refit_button.clicked.connect(self.start_refit)
        self.progress = QProgressBar()
        self.progress.setTextVisible(True)
        self.progress.setFormat("idle")
        self.progress.setValue(0)
        form.addRow(self.refit_button, self.progress)
        ll.addWidget(refit_box)

        exp = QGroupBox("Export")
        el = QHBoxLayout(exp)
        self.export_fig_button = QPushButton("Figure…")
        self.export_fig_button.setToolTip("the report figure of the shown fit (.png, .pdf, .svg)")
        self.export_fig_button.clicked.connect(lambda: self.export_figure())
        self.export_csv_button = QPushButton("CSV…")
        self.export_csv_button.setToolTip("the run's samples as CSV")
        self.export_csv_button.clicked.connect(lambda: self.export_csv())
        el.addWidget(self.export_fig_button)
        el.addWidget(self.export_csv_button)
        ll.addWidget(exp)

        scroll = QScrollArea()
        scroll.setWidgetResizable(True)
        scroll.setWidget(left)
        scroll.setMinimumWidth(260)
        split.addWidget(scroll)

        # ------------------------------------------------------------ right side
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
        self.tabs.addTab(run_page, "Run")
        self.fit_panel = FitPanel(title="No fit shown")
        self.tabs.addTab(self.fit_panel, "Fit")
        split.addWidget(self.tabs)
        split.setStretchFactor(0, 0)
        split.setStretchFactor(1, 1)
        split.setSizes([300, 900])

        self.follow_timer = QTimer(self)
        self.follow_timer.setInterval(2000)
        self.follow_timer.timeout.connect(self._follow_tick)
        self.follow_timer.start()
        folder = settings.value("archive/folder", "")
        if folder:
            self.set_folder(folder)
        self._update_buttons()

    # ------------------------------------------------------------------ files
    def choose_file(self) -> None:
        start = str(self.settings.value("archive/folder", "") or Path.cwd())
        path, _ = QFileDialog.getOpenFileName(self, "Open a run", start, "Run files (*.h5 *.hdf5 *.nxs);;All files (*)")
        if path:
            self.open(path)

    def choose_folder(self) -> None:
        start = str(self.settings.value("archive/folder", "") or Path.cwd())
        folder = QFileDialog.getExistingDirectory(self, "Folder of runs", start)
        if folder:
            self.set_folder(folder)

    def set_folder(self, folder) -> None:
        folder = Path(folder)
        self.settings.setValue("archive/folder", str(folder))
        self.folder_label.setText(f"Runs in {folder}")
        self.refresh_list(folder)

    def refresh_list(self, folder=None) -> None:
        """List the folder's runs on a worker thread (a network share can be slow), then show them."""
        folder = Path(folder or self.settings.value("archive/folder", "") or ".")
        tasks.submit(list_runs, folder, owner=self, on_done=lambda files, f=folder: self._listed(f, files),
                     on_error=lambda exc: self.message.emit(describe_error(exc)[1], "warning"))

    def _listed(self, folder: Path, files) -> None:
        if str(folder) != str(self.settings.value("archive/folder", "")):
            return  # another folder was chosen meanwhile
        self.files.clear()
        for p in files[:500]:
            it = QListWidgetItem(p.name)
            it.setData(Qt.UserRole, str(p))
            it.setToolTip(str(p))
            self.files.addItem(it)

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
        tasks.submit(load_run, path, owner=self, on_done=lambda lr: self._loaded(lr, path, select, quiet), on_error=self._load_failed)

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
        dur = run.duration_after_trigger_s
        if dur > 0 and self.window_spin.value() > dur:
            self.window_spin.setValue(round(min(20.0, dur), 2))
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
                and self.isVisible()):
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

    def options(self) -> RefitOptions:
        return RefitOptions(
            models=self.models_edit.text().strip() or "0-6", window_s=self.window_spin.value(),
            method=self.method_combo.currentText(), reduced=self.reduced_check.isChecked(),
            starts=self.starts_spin.value() or None, save=self.save_check.isChecked(),
        )

    def start_refit(self) -> None:
        if self.path is None or self.busy:
            return
        opts = self.options()
        self.settings.setValue("archive/models", opts.models)
        self.settings.setValue("archive/window_s", opts.window_s)
        self.settings.setValue("archive/method", opts.method)
        self.busy = True
        self._update_buttons()
        self.progress.setRange(0, 0)
        self.progress.setFormat("starting…")
        self.message.emit(f"Re-fitting {self.path.name}: models {opts.models}, window {opts.window_s:g} s, "
                          f"method {opts.method}", "info")
        path = self.path
        tasks.submit(refit, path, opts, owner=self, on_done=lambda out: self._refit_done(out, path),
                     on_error=self._refit_failed, on_progress=self._refit_progress)

    def _refit_progress(self, done: int, total: int, name: str) -> None:
        self.progress.setRange(0, total)
        self.progress.setValue(done)
        self.progress.setFormat(f"{done}/{total}: fitted {name}")

    def _refit_failed(self, exc) -> None:
        self.busy = False
        self.progress.setRange(0, 1)
        self.progress.setValue(0)
        self.progress.setFormat("failed")
        self._update_buttons()
        level, text = describe_error(exc)
        self.message.emit(f"Re-fit failed: {text}", level)

    def _refit_done(self, out, path) -> None:
        self.busy = False
        self.progress.setRange(0, 1)
        self.progress.setValue(1)
        r = out.result
        self.progress.setFormat(f"done in {r.duration_s:.1f} s: best {r.best.name}")
        self._update_buttons()
        name = out.saved_as or "(unsaved)"
        self.current_fit = (name, r)
        if path == self.path:
            self.fit_panel.set_fit(out.t, out.h, out.rig, r, title=f"{path.name} — re-fit {name}")
            self.tabs.setCurrentWidget(self.fit_panel)
        text = f"Re-fit of {path.name}: best {r.best.name} (a = {r.best.wave_speed_m_s:.1f} m/s) in {r.duration_s:.1f} s"
        text += f", saved as /entry/fits/{out.saved_as}" if out.saved_as else ""
        self.message.emit(text, "info")
        if out.note:
            self.message.emit(out.note, "warning")
        if out.saved_as and self.loaded_run is not None:
            self.loaded_run.fits[out.saved_as] = r
            self.fit_combo.blockSignals(True)
            if self.fit_combo.findText(out.saved_as) < 0:
                self.fit_combo.addItem(out.saved_as)
            self.fit_combo.setCurrentText(out.saved_as)
            self.fit_combo.blockSignals(False)
        self.refitted.emit(r.best.name)

    # ------------------------------------------------------------------ export
    def export_figure(self, path=None) -> None:
        if self.current_fit is None or self.path is None:
            self.message.emit("No fit to export: open a run with a fit, or re-fit it first.", "warning")
            return
        if path is None:
            start = str(self.path.with_name(self.path.stem + "_fit.png"))
            path, _ = QFileDialog.getSaveFileName(self, "Export the report figure", start, "PNG (*.png);;PDF (*.pdf);;SVG (*.svg)")
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
            path, _ = QFileDialog.getSaveFileName(self, "Export the run as CSV", start, "CSV (*.csv)")
            if not path:
                return
        tasks.submit(export_csv, self.loaded_run.run, path, owner=self, on_done=self._exported, on_error=self._export_failed)

    def _exported(self, path) -> None:
        self.message.emit(f"Exported {path}", "info")
        self.exported.emit(str(path))

    def _export_failed(self, exc) -> None:
        level, text = describe_error(exc)
        self.message.emit(f"Export failed: {text}", level)

    def _update_buttons(self) -> None:
        have = self.path is not None
        self.refit_button.setEnabled(have and not self.busy)
        self.reload_button.setEnabled(have)
        self.export_csv_button.setEnabled(self.loaded_run is not None)
        self.export_fig_button.setEnabled(self.current_fit is not None or self.loaded_run is not None)
