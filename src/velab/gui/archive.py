"""The Archive tab: the catalogue view (velab.gui.catalogue_view: browser, filters, columns), the run view
(velab.gui.run_view: run viewer, stored-fit viewer, exports) and the fit controller (velab.gui.fit_controller:
the Re-fit form and the runner of re-fits, many-run re-fits and joint fits, through velab.fitservice),
placed in one page and wired together: this module holds no state of its own but the layout."""

from __future__ import annotations

from PySide6.QtCore import QSettings, Qt, Signal
from PySide6.QtWidgets import QScrollArea, QSplitter, QVBoxLayout, QWidget

from velab.gui.catalogue_view import TABLE_ROWS, CatalogueView
from velab.gui.fit_controller import FitController
from velab.gui.run_view import RunView


class ArchiveBrowser(QWidget):
    """The three parts: ``catalogue`` (CatalogueView), ``run`` (RunView), ``fits`` (FitController).
    Signals (the window's message log and banner, scripts and tests): ``message(text, level)``,
    ``indexed(rows)``, ``loaded(path)``, ``refitted(best)``, ``exported(path)``."""

    message = Signal(str, str)
    indexed = Signal(int)
    loaded = Signal(str)
    refitted = Signal(str)
    exported = Signal(str)

    def __init__(self, settings: QSettings, parent=None):
        super().__init__(parent)
        self.settings = settings
        self.catalogue = CatalogueView(settings)
        self.run = RunView(settings, self)
        self.fits = FitController(settings)
        self._layout()
        self._wire()
        folder = settings.value("archive/folder", "")
        if folder:
            self.catalogue.set_folder(folder)

    def _layout(self) -> None:
        outer = QVBoxLayout(self)
        outer.setContentsMargins(2, 2, 2, 2)
        self.catalogue_split = QSplitter(Qt.Vertical)
        outer.addWidget(self.catalogue_split)
        self.catalogue_split.addWidget(self.catalogue)
        split = self.splitter = QSplitter(Qt.Horizontal)
        self.catalogue_split.addWidget(split)
        self.catalogue_split.setStretchFactor(0, 1)
        self.catalogue_split.setStretchFactor(1, 1)
        self.catalogue_split.setChildrenCollapsible(False)
        self._split_moved = False  # the operator moved the split: the window leaves it where they put it
        self.catalogue_split.splitterMoved.connect(lambda *_: setattr(self, "_split_moved", True))
        # the left column: compact (no group boxes but the Re-fit one) so that at 1366 x 768 every control of the
        # run shown (Open, Folder, Reload, Follow, the stored fits, Re-fit, Export) is on screen without scrolling
        left = QWidget()
        ll = QVBoxLayout(left)
        ll.setContentsMargins(2, 2, 2, 2)
        ll.setSpacing(3)
        ll.addWidget(self.run.file_bar)
        ll.addWidget(self.fits)
        ll.addWidget(self.run.export_bar)
        ll.addStretch(1)
        scroll = QScrollArea()  # only below the laptop's screen (1366 x 700 and less) does it scroll
        scroll.setWidgetResizable(True)
        scroll.setWidget(left)
        # as wide as its controls (no horizontal scrolling: a cut Reload or CSV… button looks like none)
        scroll.setMinimumWidth(left.sizeHint().width() + scroll.verticalScrollBar().sizeHint().width() + 4)
        scroll.setHorizontalScrollBarPolicy(Qt.ScrollBarAlwaysOff)
        self.detail_scroll = scroll
        split.addWidget(scroll)
        split.addWidget(self.run.tabs)
        split.setStretchFactor(0, 0)
        split.setStretchFactor(1, 1)
        split.setSizes([scroll.minimumWidth(), 900])

    def _wire(self) -> None:
        cat, run, fits = self.catalogue, self.run, self.fits
        for part in (cat, run, fits):
            part.message.connect(self.message)
        cat.indexed.connect(self.indexed)
        cat.open_requested.connect(self.open)
        cat.run_selected.connect(lambda p: self.open(p) if str(run.path) != p else None)
        cat.selection_changed.connect(run.trends.set_rows)
        cat.refit_requested.connect(fits.refit_many)
        cat.joint_requested.connect(fits.fit_together)
        cat.trends_requested.connect(lambda: run.tabs.setCurrentWidget(run.trends))
        cat.exported.connect(self.exported)
        run.folder_requested.connect(cat.choose_folder)
        run.loaded.connect(self.loaded)
        run.run_loaded.connect(lambda lr: fits.set_run(run.path, lr.run.duration_after_trigger_s))
        run.exported.connect(self.exported)
        fits.shown.connect(run.show_refit)
        fits.stored.connect(lambda: cat.refresh_list())
        fits.refitted.connect(self.refitted)
        fits.busy_changed.connect(cat.set_busy)
        fits.busy_changed.connect(lambda busy: setattr(run, "busy", busy))

    # ------------------------------------------------------------------ the window's verbs
    def set_folder(self, folder) -> None:
        self.catalogue.set_folder(folder)

    def open(self, path) -> None:
        self.fits.set_run(path)
        self.run.open(path)

    def choose_file(self) -> None:
        self.run.choose_file()

    def choose_folder(self) -> None:
        self.catalogue.choose_folder()

    # ------------------------------------------------------------------ layout
    def resizeEvent(self, event) -> None:
        super().resizeEvent(event)
        if not self._split_moved:
            self._place_split()

    def _place_split(self) -> None:
        """The catalogue as tall as TABLE_ROWS rows (more when the window is taller: half of it), the run's
        controls and views below; the operator's own placement is kept once they move the split."""
        total = self.catalogue_split.height()
        panel = self.catalogue
        table_h = panel.table.height()
        need = panel.height() - table_h + panel.table_height(TABLE_ROWS) if panel.height() else 0
        if total <= 0 or need <= 0:
            return
        top = max(need, total // 2) if total - need > 300 else need
        top = min(top, total - 120)
        self.catalogue_split.setSizes([top, total - top])
