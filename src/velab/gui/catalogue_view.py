"""The Archive tab's catalogue view: the run catalogue of a folder (velab.catalogue, indexed on a worker
thread) as a sortable, filterable table (velab.gui.catalogue_table), with the actions on the selected
rows. It fits nothing and opens nothing itself: it asks, by its signals.

Signals: ``message(text, level)``; ``indexed(rows)`` once a folder's indexing finished; ``open_requested(path)``;
``run_selected(path)`` (one run selected); ``selection_changed(rows)`` (the selected rows, all shown rows when none is); ``refit_requested(paths)``,
``joint_requested(paths)`` (the selected runs); ``trends_requested()``; ``exported(path)``.
"""

from __future__ import annotations

from pathlib import Path

from PySide6.QtCore import QObject, QSettings, Qt, QTimer, Signal
from PySide6.QtWidgets import (QAbstractItemView, QFileDialog, QHBoxLayout, QHeaderView, QLabel, QLineEdit,
                               QPushButton, QTableView, QVBoxLayout, QWidget)

from velab.catalogue.query import STATUSES, Filters, parse_range, parse_when
from velab.gui import tasks
from velab.gui.archive_io import export_rows, index_folder
from velab.gui.catalogue_table import COLUMNS, WIDEST, CatalogueModel
from velab.gui.messages import describe_error
from velab.gui.widgets import ComboBox

BEST_TIP = "best model of the latest fit, one or several: EL, S1..S6, S1r..S5r, or none (not fitted): S3, S2"
TABLE_ROWS = 10  # catalogue rows on screen at 1366 x 768 (issue 50)
JOINT_FIT_TIP = "Fit several runs together: select two or more different runs of one pipe (velab fit --joint)"
JOINT_FIT_READY_TIP = ("Fit the selected runs together: one wall for all, each run its own steady state, manoeuvre and "
                       "noise (velab fit --joint with the Re-fit settings' models and window; saved into each run)")


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


def recording_key(row: dict) -> tuple:
    """What tells two rows apart as recordings: copies of one run share it, whatever their titles (a joint fit
    refuses one record twice); start times are kept to the millisecond."""
    return row.get("start_time"), row.get("n_samples"), row.get("sample_rate_hz"), row.get("steady_flow_l_s")


class _Rows(QObject):
    """Carries row batches from the indexing worker thread to the GUI thread (a queued signal)."""

    rows = Signal(object, bool, str, int)  # rows, replace, folder, generation


class CatalogueView(QWidget):
    message = Signal(str, str)
    indexed = Signal(int)
    open_requested = Signal(str)
    run_selected = Signal(str)  # one run selected (opened unless it is the one shown)
    selection_changed = Signal(object)
    refit_requested = Signal(object)
    joint_requested = Signal(object)
    trends_requested = Signal()
    exported = Signal(str)

    def __init__(self, settings: QSettings, parent=None):
        super().__init__(parent)
        self.settings = settings
        self.busy = False  # a fit runs (the fit controller's): no second one is offered
        self._generation = 0  # a newer folder or rescan makes an older indexing stop
        self._filter_problems: list[str] = []
        self._relay = _Rows(self)
        self._relay.rows.connect(self._rows_arrived)
        self._build()
        self.filter_timer = QTimer(self)  # filters apply once typing pauses
        self.filter_timer.setSingleShot(True)
        self.filter_timer.setInterval(250)
        self.filter_timer.timeout.connect(self.apply_filters)
        self._update_buttons()

    def _build(self) -> None:
        lay = QVBoxLayout(self)
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
                head_w = self.table.horizontalHeader().fontMetrics().horizontalAdvance(COLUMNS[c][0]) + 24
                self.table.setColumnWidth(c, max(fm.horizontalAdvance(text) + 14, head_w))
        self.table.setMinimumHeight(90)
        # once rows are in, each column as wide as the rows on screen need (the rig's name whole); later the
        # operator's widths are kept
        self.table.horizontalHeader().setResizeContentsPrecision(TABLE_ROWS * 3)
        self._columns_fitted = False
        self.model.layoutChanged.connect(self._fit_columns)
        self.table.activated.connect(lambda ix: self.open_requested.emit(self.model.row(ix.row())["path"]))
        self.table.selectionModel().selectionChanged.connect(self._selection_changed)
        lay.addWidget(self.table, 1)
        acts = QHBoxLayout()
        self.open_selected_button = QPushButton("Open")
        self.open_selected_button.clicked.connect(self._open_selected)
        self.refit_selected_button = QPushButton("Re-fit selected")
        self.refit_selected_button.setToolTip("re-fit each selected run in turn with the Re-fit settings below")
        self.refit_selected_button.clicked.connect(lambda: self.refit_requested.emit(self.selected_runs()))
        self.joint_fit_button = QPushButton("Fit together")
        self.joint_fit_button.setEnabled(False)
        self.joint_fit_button.setToolTip(JOINT_FIT_TIP)
        self.joint_fit_button.clicked.connect(lambda: self.joint_requested.emit(self.selected_runs()))
        self.export_rows_button = QPushButton("Export rows…")
        self.export_rows_button.setToolTip("the selected rows (every column, as velab runs --csv) as CSV")
        self.export_rows_button.clicked.connect(lambda: self.export_selected_rows())
        self.trends_button = QPushButton("Trends")
        self.trends_button.setToolTip("plot a fitted quantity of the selected runs (all shown when none is selected)")
        self.trends_button.clicked.connect(self.trends_requested.emit)
        for b in (self.open_selected_button, self.refit_selected_button, self.joint_fit_button,
                  self.export_rows_button, self.trends_button):
            acts.addWidget(b)
        acts.addStretch(1)
        lay.addLayout(acts)

    # ------------------------------------------------------------------ the folder
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
        self.show_count()

    def _index_progress(self, gen, done, total) -> None:
        if gen == self._generation:
            self.index_label.setText(f"indexing: {done}/{total} new or changed files read")

    def _indexed(self, gen, listing) -> None:
        if gen != self._generation:
            return
        if not self._same_rows(listing):  # files gone since the index last saw them leave the table
            self.model.set_rows(listing.rows)
        self.show_count(f"; {listing.read} file(s) read in {listing.seconds:.1f} s"
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

    def show_count(self, extra: str = "") -> None:
        n_all = len(self.model.all)
        damaged = sum(1 for r in self.model.all.values() if r.get("status") == "damaged")
        bad = "; ".join(self._filter_problems)
        self.index_label.setText(f"{self.model.rowCount()} of {n_all} runs shown ({damaged} damaged){extra}"
                                 + (f" — filter {bad}" if bad else ""))
        self.index_label.setStyleSheet("color: rgb(150, 20, 20);" if bad else "")

    def _fit_columns(self, *_) -> None:
        if self._columns_fitted or not self.model.rowCount():
            return
        self._columns_fitted = True
        widths = [self.table.columnWidth(c) for c in range(self.model.columnCount())]
        self.table.resizeColumnsToContents()
        for c, w in enumerate(widths[:-1]):  # never narrower than the start time's whole text
            if self.table.columnWidth(c) < w:
                self.table.setColumnWidth(c, w)

    def table_height(self, rows: int) -> int:
        t = self.table
        return (t.horizontalHeader().sizeHint().height() + rows * t.verticalHeader().defaultSectionSize()
                + 2 * t.frameWidth() + (t.horizontalScrollBar().sizeHint().height() + 2))

    # ------------------------------------------------------------------ filters
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
        self.show_count()
        self._selection_changed()

    # ------------------------------------------------------------------ selection
    def selected_rows(self) -> list[dict]:
        return [self.model.row(ix.row()) for ix in self.table.selectionModel().selectedRows()]

    def selected_runs(self) -> list[str]:
        return [r["path"] for r in self.selected_rows() if r.get("kind") == "run"]

    def _selection_changed(self, *_) -> None:
        rows = self.selected_rows()
        self.selection_changed.emit(rows or self.model.rows)
        self._update_buttons()
        if len(rows) == 1 and rows[0].get("kind") == "run":
            self.run_selected.emit(rows[0]["path"])

    def _open_selected(self) -> None:
        rows = self.selected_rows()
        if rows:
            self.open_requested.emit(rows[0]["path"])

    def set_busy(self, busy: bool) -> None:
        self.busy = busy
        self._update_buttons()

    def _update_buttons(self) -> None:
        runs = [r for r in self.selected_rows() if r.get("kind") == "run"]
        self.refit_selected_button.setEnabled(bool(runs) and not self.busy)
        joint = len({recording_key(r) for r in runs}) >= 2
        self.joint_fit_button.setEnabled(joint and not self.busy)
        self.joint_fit_button.setToolTip(JOINT_FIT_READY_TIP if joint else JOINT_FIT_TIP)
        self.open_selected_button.setEnabled(len(runs) >= 1)

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

    def _exported(self, path) -> None:
        self.message.emit(f"Exported {path}", "info")
        self.exported.emit(str(path))

    def _export_failed(self, exc) -> None:
        level, text = describe_error(exc)
        self.message.emit(f"Export failed: {text}", level)
