"""Trends of the selected runs: a fitted quantity against the run's date or its steady flow (pyqtgraph).

:func:`trend_points` (no Qt) picks the points from catalogue rows; :class:`TrendsView` plots them.
"""

from __future__ import annotations

import math

from velab.catalogue.query import row_time

MAX_ELEMENTS = 6
# quantity key -> label; J<i>/tau<i> are the latest fit's best model's i-th Kelvin-Voigt element
QUANTITIES = {"wave_speed": "wave speed a (m/s) ± SE"}
QUANTITIES.update({f"J{i}": f"J{i} (1/Pa), element {i}" for i in range(1, MAX_ELEMENTS + 1)})
QUANTITIES.update({f"tau{i}": f"τ{i} (s), element {i}" for i in range(1, MAX_ELEMENTS + 1)})
QUANTITIES["noise_ratio"] = "noise ratio F / noise variance"
X_AXES = {"date": "run date", "flow": "steady flow Q0 (l/s)"}


def _finite(v) -> float | None:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) else None


def trend_points(rows, quantity: str, x: str = "date") -> tuple[list[float], list[float], list[float | None], list[str]]:
    """(x, y, y's standard error or None, path) of every row that has both values, in x order."""
    pts = []
    for r in rows:
        xv = row_time(r) if x == "date" and r.get("start_time") else \
            _finite(r.get("measured_flow_l_s") or r.get("steady_flow_l_s")) if x == "flow" else None
        se = None
        if quantity == "wave_speed":
            y, se = _finite(r.get("wave_speed_m_s")), _finite(r.get("wave_speed_se_m_s"))
        elif quantity == "noise_ratio":
            y = _finite(r.get("noise_ratio"))
        else:
            key, i = ("J_per_pa", int(quantity[1:])) if quantity.startswith("J") else ("tau_s", int(quantity[3:]))
            els = r.get("elements") or []
            y = _finite(els[i - 1].get(key)) if i <= len(els) and isinstance(els[i - 1], dict) else None
        if xv is not None and y is not None:
            pts.append((xv, y, se, r["path"]))
    pts.sort()
    return [p[0] for p in pts], [p[1] for p in pts], [p[2] for p in pts], [p[3] for p in pts]


try:  # Qt part: only where the GUI is installed (trend_points is used without it)
    import numpy as np
    import pyqtgraph as pg
    from PySide6.QtWidgets import QHBoxLayout, QLabel, QVBoxLayout, QWidget

    from velab.gui.widgets import ComboBox
except ImportError:  # pragma: no cover
    pg = None


if pg is not None:
    class TrendsView(QWidget):
        """Quantity and x-axis choosers over one plot of the rows given to :meth:`set_rows`."""

        def __init__(self, parent=None):
            super().__init__(parent)
            self.rows: list[dict] = []
            lay = QVBoxLayout(self)
            lay.setContentsMargins(2, 2, 2, 2)
            bar = QHBoxLayout()
            self.quantity = ComboBox()
            for k, label in QUANTITIES.items():
                self.quantity.addItem(label, k)
            self.x_axis = ComboBox()
            for k, label in X_AXES.items():
                self.x_axis.addItem(label, k)
            self.count = QLabel()
            bar.addWidget(QLabel("plot"))
            bar.addWidget(self.quantity)
            bar.addWidget(QLabel("against"))
            bar.addWidget(self.x_axis)
            bar.addWidget(self.count, 1)
            lay.addLayout(bar)
            self.date_axis = pg.DateAxisItem(orientation="bottom")
            self.plot = pg.PlotWidget(axisItems={"bottom": self.date_axis})
            self.plot.setBackground("w")
            self.plot.showGrid(x=True, y=True, alpha=0.3)
            lay.addWidget(self.plot, 1)
            self.points = pg.ScatterPlotItem(size=8, brush=pg.mkBrush(30, 90, 200), pen=None)
            self.errors = pg.ErrorBarItem(pen=pg.mkPen(30, 90, 200), beam=0)
            self.plot.addItem(self.errors)
            self.plot.addItem(self.points)
            self.data = ([], [], [], [])
            self.quantity.currentIndexChanged.connect(self.redraw)
            self.x_axis.currentIndexChanged.connect(self.redraw)

        def set_rows(self, rows) -> None:
            self.rows = list(rows)
            self.redraw()

        def redraw(self, *_) -> None:
            q, x = self.quantity.currentData(), self.x_axis.currentData()
            xs, ys, ses, paths = self.data = trend_points(self.rows, q, x)
            # a date axis only for dates (a DateAxisItem would label l/s as 1970)
            self.plot.setAxisItems({"bottom": self.date_axis if x == "date" else pg.AxisItem("bottom")})
            self.plot.setLabel("bottom", X_AXES[x])
            logy = q.startswith(("J", "tau"))  # J and tau span decades: their log10 is plotted
            self.plot.setLabel("left", ("log10 " if logy else "") + QUANTITIES[q])
            ys_plot = [math.log10(y) if logy and y > 0 else y for y in ys]
            self.points.setData(x=xs, y=ys_plot, data=paths)
            if not logy and any(s is not None for s in ses):
                self.errors.setData(x=np.asarray(xs, float), y=np.asarray(ys, float),
                                    height=np.asarray([2 * (s or 0.0) for s in ses], float))
                self.errors.setVisible(True)
            else:
                self.errors.setVisible(False)
            self.count.setText(f"{len(xs)} of {len(self.rows)} selected runs have this value")
            self.plot.enableAutoRange()
