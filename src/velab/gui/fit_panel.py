"""The fit panel: the model table (k, F, AIC, delta AIC, weight, support) and the paper's plots.

Plots (pyqtgraph): measured and fitted head for the models ticked in the table;
delta AIC against m; the calibrated creep elements J against tau; |phi(omega)|.
The model curves are computed by :func:`fit_view_data` on a worker thread (it is
model evaluation over the whole window); the panel only draws.
"""

from __future__ import annotations

import math

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import Qt, Signal
from PySide6.QtGui import QBrush, QColor, QFont
from PySide6.QtWidgets import (QAbstractItemView, QHeaderView, QLabel, QSplitter, QTableWidget, QTableWidgetItem,
                               QVBoxLayout, QWidget)

from velab.gui import tasks

COLUMNS = ("plot", "model", "k", "F (m²)", "AIC", "ΔAIC", "weight", "support", "a (m/s)", "lag-1")
PALETTE = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf",
           "#7f7f7f", "#bcbd22", "#393b79", "#637939")
BEST_BG = QColor("#d8f0d2")
MAX_DISPLAY_POINTS = 4000


def fit_view_data(t, h, rig, result) -> dict:
    """Everything the panel draws, computed off the GUI thread.

    ``t`` (s from the trigger) and ``h`` (head perturbation, m) are the calibration
    window; the curves are evaluated on it, subsampled to at most a few thousand points.
    """
    from velab.model import phi, valve_head

    t = np.asarray(t, dtype=float)
    h = np.asarray(h, dtype=float)
    q = max(1, int(math.ceil(t.size / MAX_DISPLAY_POINTS)))
    td = t[::q]
    curves, phis = {}, {}
    omega = 2 * np.pi * np.logspace(-2, 2, 200)
    for f in result.models:
        mat = f.material()
        try:
            curves[f.name] = valve_head(td, rig, mat)
        except Exception:  # a model the time grid cannot hold: leave it out of the plot
            continue
        if f.m:
            phis[f.name] = np.abs(phi(omega, rig, mat))
    return {"t": td, "h": h[::q], "curves": curves, "freq_hz": omega / (2 * np.pi), "phi": phis, "result": result}


class FitPanel(QWidget):
    """``set_fit(t, h, rig, result)`` shows a SweepResult; ``best_name()`` and the table for tests."""

    shown = Signal(str)  # best model name, once the plots are drawn

    def __init__(self, parent=None, title: str = "Model selection by AIC"):
        super().__init__(parent)
        self.result = None
        self.data: dict | None = None
        self._serial = 0
        self._checked: set[str] = set()
        self._updating = False

        lay = QVBoxLayout(self)
        lay.setContentsMargins(2, 2, 2, 2)
        self.header = QLabel(title)
        self.header.setWordWrap(True)
        f = self.header.font()
        f.setBold(True)
        self.header.setFont(f)
        lay.addWidget(self.header)

        split = QSplitter(Qt.Vertical)
        self.splitter = split
        lay.addWidget(split, 1)
        self.table = QTableWidget(0, len(COLUMNS))
        self.table.setHorizontalHeaderLabels(COLUMNS)
        self.table.verticalHeader().setVisible(False)
        self.table.setEditTriggers(QAbstractItemView.NoEditTriggers)
        self.table.setSelectionBehavior(QAbstractItemView.SelectRows)
        hh = self.table.horizontalHeader()
        hh.setSectionResizeMode(QHeaderView.ResizeToContents)
        hh.setSectionResizeMode(COLUMNS.index("support"), QHeaderView.Stretch)
        self.table.verticalHeader().setDefaultSectionSize(22)
        self.table.itemChanged.connect(self._item_changed)
        split.addWidget(self.table)

        self.plots = pg.GraphicsLayoutWidget()
        split.addWidget(self.plots)
        split.setStretchFactor(0, 1)
        split.setStretchFactor(1, 3)
        split.setSizes([200, 460])  # the table shows EL..S6 on a laptop screen
        self.p_head = self.plots.addPlot(row=0, col=0, title="measured and fitted head")
        self.p_aic = self.plots.addPlot(row=0, col=1, title="ΔAIC against m")
        self.p_creep = self.plots.addPlot(row=1, col=0, title="creep elements J against τ")
        self.p_phi = self.plots.addPlot(row=1, col=1, title="|φ(ω)|")
        self.p_head.setLabel("bottom", "time from trigger", units="s")
        self.p_head.setLabel("left", "head − steady", units="m")
        self.p_aic.setLabel("bottom", "m (Kelvin-Voigt elements)")
        self.p_aic.setLabel("left", "log10(1 + ΔAIC)")
        self.p_creep.setLabel("bottom", "τ (s), log")
        self.p_creep.setLabel("left", "J (1/Pa), log")
        self.p_creep.setLogMode(x=True, y=True)
        self.p_phi.setLabel("bottom", "f (Hz), log")
        self.p_phi.setLabel("left", "|φ|, log")
        self.p_phi.setLogMode(x=True, y=True)
        for p in (self.p_head, self.p_aic, self.p_creep, self.p_phi):
            p.showGrid(x=True, y=True, alpha=0.25)
            p.getAxis("left").setWidth(58)
        for p in (self.p_creep, self.p_phi):
            for ax in ("left", "bottom"):
                p.getAxis(ax).enableAutoSIPrefix(False)
        self.p_head.setClipToView(True)
        self.p_head.setDownsampling(auto=True, mode="peak")
        self.head_legend = self.p_head.addLegend(offset=(-5, 5), labelTextSize="8pt")
        self.creep_legend = self.p_creep.addLegend(offset=(5, 5), labelTextSize="8pt")

    # ------------------------------------------------------------------ API
    def clear(self, text: str = "") -> None:
        self.result = None
        self.data = None
        self._serial += 1
        self.table.setRowCount(0)
        for p in (self.p_head, self.p_aic, self.p_creep, self.p_phi):
            p.clear()
        if text:
            self.header.setText(text)

    def set_fit(self, t, h, rig, result, title: str = "", compute_async: bool = True) -> None:
        """Show ``result``; the model curves are computed on a worker thread."""
        self.result = result
        self._serial += 1
        serial = self._serial
        best = result.best
        self._checked = {best.name}
        others = sorted((f for f in result.models if f is not best and not f.reduced), key=lambda f: f.aic)
        if others:
            self._checked.add(others[0].name)
        self.header.setText(
            (title + "\n" if title else "")
            + f"Best model {best.name} (minimum AIC): a = {best.wave_speed_m_s:.1f} m/s, F = {best.F:.3g} m²;  "
            f"n = {result.n}, window {result.window_s:g} s, method {result.method}. "
            f"Residual lag-1 autocorrelation {best.lag1_autocorr:.2f}"
            + (" (correlated: AIC over-rewards extra parameters)" if abs(best.lag1_autocorr) > 0.2 else "")
        )
        self._fill_table(result)
        self._draw_result_plots(result)
        self.p_head.clear()
        if compute_async:
            tasks.submit(fit_view_data, t, h, rig, result,
                         on_done=lambda d, s=serial: self._curves_ready(d, s), on_error=lambda e: None)
        else:
            self._curves_ready(fit_view_data(t, h, rig, result), serial)

    def best_name(self) -> str | None:
        if self.table.rowCount() == 0:
            return None
        for r in range(self.table.rowCount()):
            if self.table.item(r, 1).font().bold():
                return self.table.item(r, 1).text()
        return None

    def model_names(self) -> list[str]:
        return [self.table.item(r, 1).text() for r in range(self.table.rowCount())]

    def set_checked(self, names) -> None:
        self._checked = set(names)
        self._updating = True
        for r in range(self.table.rowCount()):
            it = self.table.item(r, 0)
            it.setCheckState(Qt.Checked if self.table.item(r, 1).text() in self._checked else Qt.Unchecked)
        self._updating = False
        self._draw_head()

    # ------------------------------------------------------------------ drawing
    def _fill_table(self, result) -> None:
        self._updating = True
        self.table.setRowCount(len(result.models))
        best = result.best.name
        bold = QFont(self.table.font())
        bold.setBold(True)
        for r, f in enumerate(result.models):
            values = ("", f.name, str(f.k), f"{f.F:.4g}", f"{f.aic:.1f}", f"{f.delta_aic:.2f}", f"{f.weight:.3f}",
                      f.support, f"{f.wave_speed_m_s:.1f}", f"{f.lag1_autocorr:.2f}")
            for c, v in enumerate(values):
                it = QTableWidgetItem(v)
                if c == 0:
                    it.setFlags(Qt.ItemIsUserCheckable | Qt.ItemIsEnabled | Qt.ItemIsSelectable)
                    it.setCheckState(Qt.Checked if f.name in self._checked else Qt.Unchecked)
                    it.setToolTip("show this model in the head plot")
                elif c >= 2 and c != 7:
                    it.setTextAlignment(Qt.AlignRight | Qt.AlignVCenter)
                if f.name == best:
                    it.setBackground(QBrush(BEST_BG))
                    it.setFont(bold)
                    if c == 1:
                        it.setText(f.name)
                        it.setToolTip("best model: minimum AIC")
                self.table.setItem(r, c, it)
        self._updating = False

    def _item_changed(self, item) -> None:
        if self._updating or item.column() != 0:
            return
        name = self.table.item(item.row(), 1).text()
        if item.checkState() == Qt.Checked:
            self._checked.add(name)
        else:
            self._checked.discard(name)
        self._draw_head()

    def _color(self, name: str) -> str:
        names = [f.name for f in self.result.models] if self.result else []
        i = names.index(name) if name in names else 0
        return PALETTE[i % len(PALETTE)]

    def _draw_result_plots(self, result) -> None:
        self.p_aic.clear()
        best = result.best
        for red, sym in ((False, "o"), (True, "s")):
            sel = [f for f in result.models if f.reduced == red]
            if not sel:
                continue
            x = np.array([f.m for f in sel], dtype=float)
            y = np.log10(1.0 + np.maximum(np.array([f.delta_aic for f in sel]), 0.0))
            self.p_aic.plot(x, y, pen=pg.mkPen("#1f4e9c" if not red else "#888", width=1.5), symbol=sym,
                            symbolSize=8, symbolBrush="#1f4e9c" if not red else "#888", name="reduced" if red else "Sm")
        self.p_aic.plot([best.m], [np.log10(1.0 + max(best.delta_aic, 0.0))], pen=None, symbol="star",
                        symbolSize=16, symbolBrush="#2a9d2a")
        for level, style, where in ((2, Qt.DotLine, 0.35), (10, Qt.DashLine, 0.6)):
            self.p_aic.addItem(pg.InfiniteLine(pos=np.log10(1 + level), angle=0,
                                               pen=pg.mkPen("#999", style=style),
                                               label=f"ΔAIC = {level}", labelOpts={"position": where, "color": "#777"}))
        self.p_creep.clear()
        self.creep_legend.clear()
        for f in result.models:
            if f.m and not f.reduced:
                tau = np.array(f.tau_s)
                J = np.array(f.J_per_pa)
                order = np.argsort(tau)
                c = self._color(f.name)
                self.p_creep.plot(tau[order], J[order], pen=pg.mkPen(c, width=1.5 if f is best else 1),
                                  symbol="o", symbolSize=7, symbolBrush=c, name=f.name)

    def _curves_ready(self, data: dict, serial: int) -> None:
        if serial != self._serial:
            return  # a newer result replaced this one
        self.data = data
        self._draw_head()
        self.p_phi.clear()
        for name, ph in data["phi"].items():
            best = self.result is not None and name == self.result.best.name
            self.p_phi.plot(data["freq_hz"], ph, pen=pg.mkPen(self._color(name), width=2 if best else 1))
        self.shown.emit(self.result.best.name if self.result else "")

    def _draw_head(self) -> None:
        self.p_head.clear()
        self.head_legend.clear()
        if not self.data:
            return
        d = self.data
        self.p_head.plot(d["t"], d["h"], pen=pg.mkPen("#9a9a9a", width=1), name="measured")
        for f in self.result.models:
            if f.name in self._checked and f.name in d["curves"]:
                self.p_head.plot(d["t"], d["curves"][f.name], pen=pg.mkPen(self._color(f.name), width=1.5),
                                 name=f"{f.name}  F={f.F:.3g} m²")
