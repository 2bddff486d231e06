"""The Archive tab's table of the run catalogue: a QAbstractTableModel over catalogue rows.

Filtering and sorting are velab.catalogue.query's (the same as ``velab runs``), done in
Python on the model's own list: a proxy model would re-sort on every added batch, row by
row through Qt. ``data()`` is asked only for the rows on screen, so thousands of rows
cost the GUI thread one sort per batch (a few ms per thousand rows).
"""

from __future__ import annotations

from PySide6.QtCore import QAbstractTableModel, QModelIndex, Qt
from PySide6.QtGui import QBrush, QColor

from velab.catalogue.columns import WINDOW_COLUMNS
from velab.catalogue.query import Filters, sort_rows

# velab.catalogue.columns declares them (and the text table of ``velab runs``): header, sort key, cell text
COLUMNS = tuple((c.header, c.sort, c.cell) for c in WINDOW_COLUMNS)
# the widest text each column shows in practice: the columns open that wide (the start time whole, with
# its seconds: two runs of one minute differ)
WIDEST = tuple(c.widest for c in WINDOW_COLUMNS)
_RED = QBrush(QColor(190, 30, 30))
_AMBER = QBrush(QColor(170, 110, 0))


class CatalogueModel(QAbstractTableModel):
    def __init__(self, parent=None):
        super().__init__(parent)
        self.all: dict[str, dict] = {}  # path -> row
        self.rows: list[dict] = []  # shown: filtered and sorted
        self.filters = Filters()
        self.sort_key = "-start"  # newest first, as the archive always listed

    # ------------------------------------------------------------------ content
    def set_rows(self, rows) -> None:
        self.all = {r["path"]: r for r in rows}
        self._refresh()

    def add_rows(self, rows) -> None:
        for r in rows:
            self.all[r["path"]] = r
        self._refresh()

    def set_filters(self, filters: Filters) -> None:
        self.filters = filters
        self._refresh()

    def _refresh(self) -> None:
        # a layout change that keeps the selection: persistent indexes follow their run's path
        self.layoutAboutToBeChanged.emit()
        old = self.persistentIndexList()
        paths = [(self.rows[i.row()]["path"], i.column()) if i.row() < len(self.rows) else (None, 0) for i in old]
        self.rows = sort_rows(self.filters.apply(list(self.all.values())), self.sort_key)
        where = {r["path"]: k for k, r in enumerate(self.rows)}
        self.changePersistentIndexList(old, [self.index(where[p], c) if p in where else QModelIndex()
                                             for p, c in paths])
        self.layoutChanged.emit()

    def row(self, i: int) -> dict:
        return self.rows[i]

    # ------------------------------------------------------------------ Qt
    def rowCount(self, parent=QModelIndex()) -> int:
        return 0 if parent.isValid() else len(self.rows)

    def columnCount(self, parent=QModelIndex()) -> int:
        return 0 if parent.isValid() else len(COLUMNS)

    def headerData(self, section, orientation, role=Qt.DisplayRole):
        if role == Qt.DisplayRole and orientation == Qt.Horizontal:
            return COLUMNS[section][0]
        return None

    def data(self, index, role=Qt.DisplayRole):
        if not index.isValid():
            return None
        r = self.rows[index.row()]
        if role == Qt.DisplayRole:
            return str(COLUMNS[index.column()][2](r))
        if role == Qt.ToolTipRole:
            if r.get("status") == "damaged":
                return f"{r['path']}: {r.get('reason')}"
            tip = r["path"]
            if r.get("reason"):
                tip += f"\n{r['status']}: {r['reason']}"
            if r.get("warnings"):
                tip += "\nfit warnings: " + ", ".join(r["warnings"])
            return tip
        if role == Qt.ForegroundRole:
            if r.get("status") in ("damaged", "failed", "aborted"):
                return _RED
            if r.get("flags"):
                return _AMBER
        return None

    def sort(self, column: int, order=Qt.AscendingOrder) -> None:
        key = COLUMNS[column][1]
        self.sort_key = key if order == Qt.AscendingOrder else "-" + key
        self._refresh()
