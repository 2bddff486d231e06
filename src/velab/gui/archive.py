"""The archive browser: the run catalogue of a folder as a sortable, filterable table (velab.catalogue,
indexed on a worker thread), open earlier runs (also one still being written), see metadata and fits,
re-fit one or several in the background, trends of the selected runs, export the report figure, a CSV
of a run's samples and a CSV of the selected rows."""

from __future__ import annotations

from pathlib import Path

from PySide6.QtCore import QObject, QSettings, Qt, QTimer, Signal
from PySide6.QtGui import QFont
from PySide6.QtWidgets import (QAbstractItemView, QCheckBox, QFileDialog, QGridLayout, QGroupBox,
                               QHBoxLayout, QHeaderView, QLabel, QLineEdit, QPlainTextEdit,
                               QProgressBar, QPushButton, QScrollArea, QSplitter, QTableView, QTabWidget, QVBoxLayout,
                               QWidget)

from velab.catalogue.query import STATUSES, Filters, parse_range, parse_when
from velab.gui import tasks
from velab.gui.archive_io import (RefitOptions, export_csv, export_report_figure, export_rows, index_folder, load_run,
                                  refit, refit_many)
from velab.gui.catalogue_table import COLUMNS, WIDEST, CatalogueModel
from velab.gui.fit_panel import FitPanel
from velab.gui.live_plot import LivePlot
from velab.gui.messages import describe_error
from velab.gui.trends import TrendsView
from velab.gui.widgets import ComboBox, DoubleSpinBox, SpinBox


class _Rows(QObject):
    """Carries row batches from the indexing worker thread to the GUI thread (a queued signal)."""

    rows = Signal(object, bool, str, int)  # rows, replace, folder, generation


BEST_TIP = "best model of the latest fit, one or several: EL, S1..S6, S1r..S5r, or none (not fitted): S3, S2"


def parse_best(text: str) -> tuple[str, ...]:
    """The best-model filter's names; ValueError naming a name that is no model (the field is then marked
    and ignored, as a date that does not parse: "S9" showing no row would look like no such run)."""
    from velab.fitting.sweep import MAX_M

    names = tuple(b.strip() for b in text.split(",") if b.strip())
    known = {"el", "none"} | {f"s{m}" for m in range(1, MAX_M + 1)} | {f"s{m}r" for m in range(1, MAX_M)}
    bad = [b for b in names if b.lower() not in known]
    if bad:
        raise ValueError(f"{', '.join(bad)}: no such model (EL, S1..S{MAX_M}, S1r..S{MAX_M - 1}r or none); "
                         "the filter is ignored")
    return names


TABLE_ROWS = 10  # catalogue rows on screen at 1366 x 768 (issue 50)
JOINT_FIT_TIP = "Fit several runs together: select two or more different runs of one pipe (velab fit --joint)"
JOINT_FIT_READY_TIP = ("Fit the selected runs together: one wall for all, each run its own steady state, manoeuvre and "
                       "noise (velab fit --joint with the Re-fit settings' models and window; saved into each run)")


def _recording_key(row: dict) -> tuple:
    """What tells two rows apart as recordings: copies of one run share it, whatever their titles (a joint fit
    refuses one record twice); start times are kept to the millisecond."""
    return row.get("start_time"), row.get("n_samples"), row.get("sample_rate_hz"), row.get("steady_flow_l_s")


def joint_fit(paths: list[str], opts: RefitOptions) -> dict:
    """``velab fit --joint`` on the runs, in a process of its own (the command's checks, saving into every run and
    one-line errors; the fit's CPU off the GUI's process); its JSON document."""
    import json
    import subprocess
    import sys

    from velab.errors import DataError

    cmd = [sys.executable, "-m", "velab.cli", "fit", "--joint", *map(str, paths), "--models", opts.models,
           "-q", "--json"]
    if opts.window_s:
        cmd += ["--window", f"{opts.window_s:g}"]
    if not opts.save:
        cmd.append("--no-save")
    out = subprocess.run(cmd, capture_output=True, text=True)
    if out.returncode != 0:
        lines = [ln for ln in out.stderr.strip().splitlines() if ln.strip()]
        raise DataError(lines[-1].removeprefix("velab: ") if lines else f"velab fit --joint: exit {out.returncode}")
    return json.loads(out.stdout)


class ArchiveBrowser(QWidget):
    """Signals ``message(text, level)`` for the window's message log and banner."""

    message = Signal(str, str)
    indexed = Signal(int)  # rows in the catalogue once a folder's indexing finished
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
        self._generation = 0  # a newer folder or rescan makes an older indexing stop
        self._relay = _Rows(self)
        self._relay.rows.connect(self._rows_arrived)

        outer = QVBoxLayout(self)
        outer.setContentsMargins(2, 2, 2, 2)
        self.catalogue_split = QSplitter(Qt.Vertical)
        outer.addWidget(self.catalogue_split)
        self.catalogue_split.addWidget(self._catalogue_panel())
        split = QSplitter(Qt.Horizontal)
        self.splitter = split
        self.catalogue_split.addWidget(split)
        self.catalogue_split.setStretchFactor(0, 1)
        self.catalogue_split.setStretchFactor(1, 1)
        self.catalogue_split.setChildrenCollapsible(False)
        self._split_moved = False  # the operator moved the split: the window leaves it where they put it
        self.catalogue_split.splitterMoved.connect(lambda *_: setattr(self, "_split_moved", True))

        # ------------------------------------------------------------ left column
        # compact (a grid, no group boxes but the Re-fit one) so that at 1366 x 768 every control of the run
        # shown (Open, Folder, Reload, Follow, the stored fits, Re-fit, Export) is on screen without scrolling
        left = QWidget()
        ll = QVBoxLayout(left)
        ll.setContentsMargins(2, 2, 2, 2)
        ll.setSpacing(3)
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
        self.follow = QCheckBox("Follow a run being written")
        self.follow.setToolTip("a run still being recorded is re-read every 2 s (SWMR)")
        self.follow.setChecked(True)
        ll.addWidget(self.follow)
        fits_row = QHBoxLayout()
        fits_row.addWidget(QLabel("stored fit"))
        self.fit_combo = ComboBox()
        self.fit_combo.currentIndexChanged.connect(self._fit_chosen)
        fits_row.addWidget(self.fit_combo, 1)
        ll.addLayout(fits_row)

        refit_box = QGroupBox("Re-fit")
        form = QGridLayout(refit_box)
        form.setContentsMargins(4, 2, 4, 4)
        form.setVerticalSpacing(3)
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
        self.reduced_check = QCheckBox("also S1r..S5r")
        self.reduced_check.setToolTip("also the reduced models S1r..S5r")
        self.save_check = QCheckBox("store in the file")
        self.save_check.setToolTip("store the fit in the run file")
        self.save_check.setChecked(True)
        for r, (label, w, label2, w2) in enumerate((("models", self.models_edit, "window", self.window_spin),
                                                     ("method", self.method_combo, "starts", self.starts_spin))):
            form.addWidget(QLabel(label), r, 0)
            form.addWidget(w, r, 1)
            form.addWidget(QLabel(label2), r, 2)
            form.addWidget(w2, r, 3)
        form.addWidget(self.reduced_check, 2, 0, 1, 2)
        form.addWidget(self.save_check, 2, 2, 1, 2)
        self.refit_button = QPushButton("Re-fit")
        self.refit_button.clicked.connect(self.start_refit)
        self.progress = QProgressBar()
        self.progress.setTextVisible(True)
        self.progress.setFormat("idle")
        self.progress.setValue(0)
        form.addWidget(self.refit_button, 3, 0, 1, 2)
        form.addWidget(self.progress, 3, 2, 1, 2)
        ll.addWidget(refit_box)

        el = QHBoxLayout()
        el.addWidget(QLabel("export"))
        self.export_fig_button = QPushButton("Figure…")
        self.export_fig_button.setToolTip("the report figure of the shown fit (.png, .pdf, .svg)")
        self.export_fig_button.clicked.connect(lambda: self.export_figure())
        self.export_csv_button = QPushButton("CSV…")
        self.export_csv_button.setToolTip("the run's samples as CSV")
        self.export_csv_button.clicked.connect(lambda: self.export_csv())
        el.addWidget(self.export_fig_button)
        el.addWidget(self.export_csv_button)
        ll.addLayout(el)
        ll.addStretch(1)

        scroll = QScrollArea()  # only below the laptop's screen (1366 x 700 and less) does it scroll
        scroll.setWidgetResizable(True)
        scroll.setWidget(left)
        # as wide as its controls (no horizontal scrolling: a cut Reload or CSV… button looks like none)
        scroll.setMinimumWidth(left.sizeHint().width() + scroll.verticalScrollBar().sizeHint().width() + 4)
        scroll.setHorizontalScrollBarPolicy(Qt.ScrollBarAlwaysOff)
        self.detail_scroll = scroll
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
        split.addWidget(self.tabs)
        split.setStretchFactor(0, 0)
        split.setStretchFactor(1, 1)
        split.setSizes([scroll.minimumWidth(), 900])

        self.follow_timer = QTimer(self)
        self.follow_timer.setInterval(2000)
        self.follow_timer.timeout.connect(self._follow_tick)
        self.follow_timer.start()
        self.filter_timer = QTimer(self)  # filters apply once typing pauses
        self.filter_timer.setSingleShot(True)
        self.filter_timer.setInterval(250)
        self.filter_timer.timeout.connect(self.apply_filters)
        folder = settings.value("archive/folder", "")
        if folder:
            self.set_folder(folder)
        self._update_buttons()

    def resizeEvent(self, event) -> None:
        super().resizeEvent(event)
        if not self._split_moved:
            self._place_split()

    def _place_split(self) -> None:
        """The catalogue as tall as TABLE_ROWS rows (more when the window is taller: half of it), the run's
        controls and views below; the operator's own placement is kept once they move the split."""
        total = self.catalogue_split.height()
        panel = self.catalogue_split.widget(0)
        table_h = self.table.height()
        need = panel.height() - table_h + self._table_height(TABLE_ROWS) if panel.height() else 0
        if total <= 0 or need <= 0:
            return
        top = max(need, total // 2) if total - need > 300 else need
        top = min(top, total - 120)
        self.catalogue_split.setSizes([top, total - top])

    def _table_height(self, rows: int) -> int:
        t = self.table
        return (t.horizontalHeader().sizeHint().height() + rows * t.verticalHeader().defaultSectionSize()
                + 2 * t.frameWidth() + (t.horizontalScrollBar().sizeHint().height() + 2))

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
        self.folder_label.setText(f"Runs under {folder}")
        self.model.set_rows([])
        self._columns_fitted = False
        self.refresh_list(folder)

    def refresh_list(self, folder=None) -> None:
        """Index the folder's runs (recursively) on a worker thread; rows are shown as they come."""
        folder = folder or self.settings.value("archive/folder", "")
        if not folder:
            return  # no folder chosen yet: nothing to index
        folder = Path(folder)
        self._generation += 1
        gen = self._generation
        self.index_label.setText("indexing…")
        emit = self._relay.rows.emit
        tasks.submit(index_folder, folder, lambda rows, replace: emit(rows, replace, str(folder), gen),
                     stop=lambda: gen != self._generation, owner=self,
                     on_done=lambda listing: self._indexed(gen, listing),
                     on_error=lambda exc: self._index_failed(gen, exc),
                     on_progress=lambda d, t, _s: self._index_progress(gen, d, t))

    def _rows_arrived(self, rows, replace: bool, folder: str, gen: int) -> None:
        if gen != self._generation or folder != str(self.settings.value("archive/folder", "")):
            return  # another folder was chosen, or the same one rescanned, meanwhile: that indexing's rows
        if replace:
            self.model.set_rows(rows)
        else:
            self.model.add_rows(rows)
        self._show_count()

    def _index_progress(self, gen, done, total) -> None:
        if gen == self._generation:
            self.index_label.setText(f"indexing: {done}/{total} new or changed files read")

    def _indexed(self, gen, listing) -> None:
        if gen != self._generation:
            return
        if not self._same_rows(listing):  # files gone since the index last saw them leave the table
            self.model.set_rows(listing.rows)
        self._show_count(f"; {listing.read} file(s) read in {listing.seconds:.1f} s"
                         + (f"; {len(listing.others)} HDF5 file(s) that are not runs skipped" if listing.others else ""))
        self.indexed.emit(len(listing.rows))

    def _same_rows(self, listing) -> bool:
        """The table already shows these rows (nothing read or removed, no status changed): no second refresh of
        thousands of rows on the GUI thread."""
        if listing.read or listing.removed or len(listing.rows) != len(self.model.all):
            return False
        shown = self.model.all
        return all(shown.get(r["path"], {}).get("status") == r.get("status") for r in listing.rows)

    def _index_failed(self, gen, exc) -> None:
        if gen == self._generation:
            self.index_label.setText("indexing failed")
            self.message.emit(describe_error(exc)[1], "warning")

    def _show_count(self, extra: str = "") -> None:
        n_all = len(self.model.all)
        damaged = sum(1 for r in self.model.all.values() if r.get("status") == "damaged")
        bad = "; ".join(getattr(self, "_filter_problems", ()))
        self.index_label.setText(f"{self.model.rowCount()} of {n_all} runs shown ({damaged} damaged){extra}"
                                 + (f" — filter {bad}" if bad else ""))
        self.index_label.setStyleSheet("color: rgb(150, 20, 20);" if bad else "")

    # ------------------------------------------------------------------ the catalogue table
    def _catalogue_panel(self) -> QWidget:
        panel = QWidget()
        lay = QVBoxLayout(panel)
        lay.setContentsMargins(0, 0, 0, 0)
        head = QHBoxLayout()
        self.folder_label = QLabel()
        self.rescan_button = QPushButton("Rescan")
        self.rescan_button.setToolTip("read new and changed run files of the folder again (the index keeps the rest)")
        self.rescan_button.clicked.connect(lambda: self.refresh_list())
        self.index_label = QLabel()
        head.addWidget(self.folder_label)
        head.addWidget(self.rescan_button)
        head.addWidget(self.index_label, 1)
        lay.addLayout(head)
        filt = QHBoxLayout()
        self.status_filter = ComboBox()
        self.status_filter.addItem("any status", "")
        for st in STATUSES:
            self.status_filter.addItem(st, st)
        self.best_filter = QLineEdit()
        self.best_filter.setPlaceholderText("best: S3, S2…")
        self.rig_filter = QLineEdit()
        self.rig_filter.setPlaceholderText("rig")
        self.since_filter = QLineEdit()
        self.since_filter.setPlaceholderText("since YYYY-MM-DD")
        self.until_filter = QLineEdit()
        self.until_filter.setPlaceholderText("until YYYY-MM-DD")
        self.q0_filter = QLineEdit()
        self.q0_filter.setPlaceholderText("Q0 l/s: 3.6, 3.4:3.8")
        self._q0_tip = ("steady flow, l/s (the measured one where recorded): MIN:MAX (either side may be empty), "
                        "VALUE~TOL, or VALUE (within 3 %), as velab runs --q0")
        self.q0_filter.setToolTip(self._q0_tip)
        self.text_filter = QLineEdit()
        self.text_filter.setPlaceholderText("text in title, operator, specimen, notes")
        self.status_filter.currentIndexChanged.connect(lambda *_: self.filter_timer.start())
        for w in (self.best_filter, self.rig_filter, self.since_filter, self.until_filter, self.q0_filter,
                  self.text_filter):
            w.textChanged.connect(lambda *_: self.filter_timer.start())
        for w, stretch in ((self.status_filter, 0), (self.best_filter, 0), (self.rig_filter, 0),
                           (self.since_filter, 0), (self.until_filter, 0), (self.q0_filter, 0), (self.text_filter, 1)):
            filt.addWidget(w, stretch)
        lay.addLayout(filt)
        self.model = CatalogueModel(self)
        self.table = QTableView()
        self.table.setModel(self.model)
        self.table.setSortingEnabled(True)
        self.table.sortByColumn(0, Qt.DescendingOrder)  # newest first
        self.table.setSelectionBehavior(QAbstractItemView.SelectRows)
        self.table.setSelectionMode(QAbstractItemView.ExtendedSelection)
        self.table.verticalHeader().setVisible(False)
        self.table.verticalHeader().setDefaultSectionSize(20)
        self.table.horizontalHeader().setSectionResizeMode(QHeaderView.Interactive)
        self.table.horizontalHeader().setStretchLastSection(True)
        fm = self.table.fontMetrics()
        for c, text in enumerate(WIDEST):  # each column opens as wide as what it shows (the start time whole)
            if text:
                head = self.table.horizontalHeader().fontMetrics().horizontalAdvance(COLUMNS[c][0]) + 24
                self.table.setColumnWidth(c, max(fm.horizontalAdvance(text) + 14, head))
        self.table.setMinimumHeight(90)
        # once rows are in, each column as wide as the rows on screen need (the rig's name whole); later the
        # operator's widths are kept
        self.table.horizontalHeader().setResizeContentsPrecision(TABLE_ROWS * 3)
        self._columns_fitted = False
        self.model.layoutChanged.connect(self._fit_columns)
        self.table.activated.connect(lambda ix: self.open(self.model.row(ix.row())["path"]))
        self.table.selectionModel().selectionChanged.connect(self._selection_changed)
        lay.addWidget(self.table, 1)
        acts = QHBoxLayout()
        self.open_selected_button = QPushButton("Open")
        self.open_selected_button.clicked.connect(self._open_selected)
        self.refit_selected_button = QPushButton("Re-fit selected")
        self.refit_selected_button.setToolTip("re-fit each selected run in turn with the Re-fit settings below")
        self.refit_selected_button.clicked.connect(lambda: self.refit_selected())
        self.joint_fit_button = QPushButton("Fit together")
        self.joint_fit_button.setEnabled(False)
        self.joint_fit_button.setToolTip(JOINT_FIT_TIP)
        self.joint_fit_button.clicked.connect(lambda: self.fit_together())
        self.export_rows_button = QPushButton("Export rows…")
        self.export_rows_button.setToolTip("the selected rows (every column, as velab runs --csv) as CSV")
        self.export_rows_button.clicked.connect(lambda: self.export_selected_rows())
        self.trends_button = QPushButton("Trends")
        self.trends_button.setToolTip("plot a fitted quantity of the selected runs (all shown when none is selected)")
        self.trends_button.clicked.connect(lambda: self.tabs.setCurrentWidget(self.trends))
        for b in (self.open_selected_button, self.refit_selected_button, self.joint_fit_button,
                  self.export_rows_button, self.trends_button):
            acts.addWidget(b)
        acts.addStretch(1)
        lay.addLayout(acts)
        return panel

    def _fit_columns(self, *_) -> None:
        if self._columns_fitted or not self.model.rowCount():
            return
        self._columns_fitted = True
        widths = [self.table.columnWidth(c) for c in range(self.model.columnCount())]
        self.table.resizeColumnsToContents()
        for c, w in enumerate(widths[:-1]):  # never narrower than the start time's whole text
            if self.table.columnWidth(c) < w:
                self.table.setColumnWidth(c, w)

    def _parsed(self, w: QLineEdit, parse, tip: str = ""):
        """parse(text) of a filter field, None when empty; a value that does not parse is marked and ignored."""
        text = w.text().strip()
        try:
            value = parse(text) if text else None
            w.setStyleSheet("")
            w.setToolTip(tip)
            return value
        except ValueError as exc:
            w.setStyleSheet("color: rgb(150, 20, 20); background: #fde2e1;")
            w.setToolTip(str(exc))
            self._filter_problems.append(f"{text!r} ignored: {exc}".replace("; the filter is ignored", ""))
            return None

    def filters(self) -> Filters:
        """The filter fields as velab.catalogue Filters; a date or range that does not parse is marked and ignored."""
        self._filter_problems = []
        when = {name: self._parsed(w, lambda t, end=end: parse_when(t, end=end))
                for name, w, end in (("since", self.since_filter, False), ("until", self.until_filter, True))}
        q0 = self._parsed(self.q0_filter, parse_range, self._q0_tip)
        status = self.status_filter.currentData()
        best = self._parsed(self.best_filter, parse_best, BEST_TIP) or ()
        return Filters(status=(status,) if status else (),
                       best=best,
                       rig=self.rig_filter.text().strip(), since=when["since"], until=when["until"],
                       text=tuple(self.text_filter.text().split()), q0=q0)

    def apply_filters(self) -> None:
        self.model.set_filters(self.filters())
        self._show_count()
        self._selection_changed()

    def selected_rows(self) -> list[dict]:
        return [self.model.row(ix.row()) for ix in self.table.selectionModel().selectedRows()]

    def _selection_changed(self, *_) -> None:
        rows = self.selected_rows()
        self.trends.set_rows(rows or self.model.rows)
        self._update_buttons()
        if len(rows) == 1 and rows[0].get("kind") == "run" and str(self.path) != rows[0]["path"]:
            self.open(rows[0]["path"])

    def _open_selected(self) -> None:
        rows = self.selected_rows()
        if rows:
            self.open(rows[0]["path"])

    def export_selected_rows(self, path=None) -> None:
        rows = self.selected_rows() or list(self.model.rows)
        if not rows:
            self.message.emit("No rows to export: choose a folder of runs first.", "warning")
            return
        if path is None:
            start = str(Path(str(self.settings.value("archive/folder", "") or Path.cwd())) / "runs.csv")
            path, _ = QFileDialog.getSaveFileName(self, "Export the selected rows", start, "CSV (*.csv)")
            if not path:
                return
        tasks.submit(export_rows, rows, path, owner=self, on_done=self._exported, on_error=self._export_failed)

    def refit_selected(self) -> None:
        paths = [r["path"] for r in self.selected_rows() if r.get("kind") == "run"]
        if not paths or self.busy:
            return
        opts = self.options()
        self.busy = True
        self._update_buttons()
        self.progress.setRange(0, len(paths))
        self.progress.setValue(0)
        self.message.emit(f"Re-fitting {len(paths)} runs: models {opts.models}, window {opts.window_s:g} s", "info")
        tasks.submit(refit_many, paths, opts, owner=self, on_done=self._refit_many_done,
                     on_error=self._refit_failed,
                     on_progress=lambda d, t, s: (self.progress.setRange(0, t), self.progress.setValue(d),
                                                  self.progress.setFormat(f"{d}/{t}: {s}")))

    def fit_together(self) -> None:
        """The joint fit of the selected runs (velab fit --joint) in the background; the rows show it when done."""
        paths = [r["path"] for r in self.selected_rows() if r.get("kind") == "run"]
        if len(paths) < 2 or self.busy:
            return
        opts = self.options()
        self.busy = True
        self._update_buttons()
        self.progress.setRange(0, 0)
        self.progress.setFormat(f"fitting {len(paths)} runs together…")
        self.message.emit(f"Fitting {len(paths)} runs together: models {opts.models}, window {opts.window_s:g} s",
                          "info")
        tasks.submit(joint_fit, paths, opts, owner=self, on_done=lambda doc: self._joint_done(doc, len(paths)),
                     on_error=self._refit_failed)

    def _joint_done(self, doc: dict, n: int) -> None:
        self.busy = False
        self.progress.setRange(0, 1)
        self.progress.setValue(1)
        best = doc.get("best") or "?"
        self.progress.setFormat(f"joint fit: best {best}")
        self._update_buttons()
        model = next((m for m in doc.get("models") or [] if m.get("name") == best), {})
        speed = model.get("wave_speed")
        text = f"Joint fit of {n} runs: best {best}" + (f" (a = {speed:.1f} m/s)" if isinstance(speed, float) else "")
        text += f", saved as /entry/fits/{doc['fit_name']} in each run" if doc.get("fit_name") else " (not saved)"
        self.message.emit(text, "info")
        for note in doc.get("notes") or []:
            self.message.emit(f"Joint fit: {note}", "info")
        self.refitted.emit(best)
        if doc.get("fit_name"):
            self.refresh_list()  # the runs' rows show the joint fit as their latest

    def _refit_many_done(self, outcomes) -> None:
        self.busy = False
        self._update_buttons()
        failed = sum(1 for _, line in outcomes if line.startswith("failed"))
        for p, line in outcomes:
            self.message.emit(f"Re-fit of {Path(p).name}: {line}", "warning" if line.startswith("failed") else "info")
        self.progress.setFormat(f"{len(outcomes) - failed} of {len(outcomes)} re-fitted")
        self.refitted.emit(f"{len(outcomes) - failed}/{len(outcomes)}")
        self.refresh_list()  # the saved fits change the rows

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
            self.tabs.setCurrentWidget(self.fit_scroll)
        text = f"Re-fit of {path.name}: best {r.best.name} (a = {r.best.wave_speed_m_s:.1f} m/s) in {r.duration_s:.1f} s"
        text += f", saved as /entry/fits/{out.saved_as}" if out.saved_as else ""
        self.message.emit(text, "info")
        if out.note:
            self.message.emit(out.note, "warning")
        if out.saved_as:
            self.refresh_list()  # the run's row shows its new fit
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
        if hasattr(self, "table"):
            runs = [r for r in self.selected_rows() if r.get("kind") == "run"]
            self.refit_selected_button.setEnabled(bool(runs) and not self.busy)
            joint = len({_recording_key(r) for r in runs}) >= 2
            self.joint_fit_button.setEnabled(joint and not self.busy)
            self.joint_fit_button.setToolTip(JOINT_FIT_READY_TIP if joint else JOINT_FIT_TIP)
            self.open_selected_button.setEnabled(len(runs) >= 1)
