"""The fit panel: the model table (fit_rows.py) and the paper's plots.

Plots (pyqtgraph): measured and fitted head for the models ticked in the table, and below it the best
model's residuals against time with the record's noise band (+- the pretrigger baseline's standard
deviation: velab.fitting.adequacy); delta AIC against m; the retarded creep compliance J(t) - J0 of every full
model against t, the best one's with its 95 % band (velab.fitting.creep; decade labels only); |phi(omega)|. The model curves are computed by
:func:`fit_view_data` on a worker thread (it is model evaluation over the whole window);
the panel only draws, and only when it is on screen. The fit's warnings (misfit, cavitation, bound)
are a red line under the header: a fit that arrives while the Run page
is shown is drawn (and its curves computed) when the Fit page is opened.
"""

from __future__ import annotations

import math

import numpy as np
import pyqtgraph as pg
import shiboken6
from PySide6.QtCore import Qt, QTimer, Signal
from PySide6.QtGui import QBrush, QColor, QFont
from PySide6.QtWidgets import (QAbstractItemView, QHeaderView, QLabel, QSizePolicy, QTableWidget,
                               QTableWidgetItem, QVBoxLayout, QWidget)

from velab.fitting.creep import creep_of
from velab.fitting.selection import averaged_creep_shown
from velab.fitting.friction import fitted_head
from velab.fitting.flows import result_flow
from velab.gui import tasks
from velab.gui.fit_rows import COLUMNS, criterion, model_rows, warnings_text
from velab.gui.fit_summary import summary_html
from velab.model import phi

PALETTE = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf",
           "#7f7f7f", "#bcbd22", "#393b79", "#637939")
BEST_BG = QColor("#d8f0d2")
MAX_DISPLAY_POINTS = 4000
ROW_H = 20


def fit_view_data(t, h, rig, result) -> dict:
    """Everything the panel draws, computed off the GUI thread.

    ``t`` (s from the trigger) and ``h`` (head perturbation, m) are the calibration
    window; the curves are evaluated on it, subsampled to at most a few thousand points.
    """

    t = np.asarray(t, dtype=float)
    h = np.asarray(h, dtype=float)
    q = max(1, int(math.ceil(t.size / MAX_DISPLAY_POINTS)))
    td = t[::q]
    curves, phis = {}, {}
    omega = 2 * np.pi * np.logspace(-2, 2, 200)
    # the fit's own flow at the valve (velab.fitting.manoeuvre), on the whole window: the closure is
    # shorter than the display's subsampling step
    flow = result_flow(result.settings, t, h, rig)
    for f in result.models:
        mat = f.material()
        try:
            curves[f.name] = fitted_head(t, rig, f, flow=flow)[::q]
        except Exception:  # a model the time grid cannot hold: leave it out of the plot
            continue
        if f.m:
            phis[f.name] = np.abs(phi(omega, rig, mat))
    # J(t) - J0 with its band, from the lower retardation-time bound to the window; a model whose every
    # element vanished creeps by ~1e-25 1/Pa and would stretch the log axis by ten decades: left out
    creep = {f.name: creep_of(result, f) for f in result.models
             if f.m and not f.reduced and not all(f.negligible or (False,))}
    # the model-averaged band where the choice of model is uncertain (velab.fitting.creep)
    avg = averaged_creep_shown(result)
    creep_averaged = avg.curve if avg is not None else None
    try:  # the best model's residuals at the fit rate, as the fitter saw them (comparable to the noise band)
        from velab.fitting.residuals import best_residuals

        res_t, res = best_residuals(t, h, rig, result)
    except Exception:  # a model the time grid cannot hold: no residual plot
        res_t = res = np.zeros(0)
    return {"t": td, "h": h[::q], "curves": curves, "freq_hz": omega / (2 * np.pi), "phi": phis, "result": result,
            "res_t": res_t, "res": res, "creep": creep, "creep_averaged": creep_averaged}


AVERAGED_LABEL = "model-averaged 95 %"


class DecadeAxis(pg.AxisItem):
    """A log axis labelled at decades (0.01, 0.1, 1, 1e-12 ...), and at 2 and 5 x 10^k only when it
    spans less than a decade: pyqtgraph's labels at every 2..9 x 10^k overlapped."""

    _major = True  # whether pyqtgraph's last tick levels had a decade level besides the minor one

    def tickValues(self, minVal, maxVal, size):
        levels = super().tickValues(minVal, maxVal, size)
        # over a few decades pyqtgraph gives the minor level alone (the creep J(t) - J0 spans two)
        self._major = any(spacing is not None for spacing, _ in levels)
        return levels

    def tickStrings(self, values, scale, spacing):
        if not self.logMode:
            return super().tickStrings(values, scale, spacing)
        values = list(values)
        if spacing is None:  # pyqtgraph's minor level: k + log10(1..9), the decades included again
            wide = bool(values) and max(values) - min(values) >= 1.0
            if wide and not self._major:  # no decade level: the decades are labelled here
                return [_fmt(v) if _is_decade(v) else "" for v in values]
            return ["" if wide or (_is_decade(v) and self._major) or (not _is_decade(v) and round(_mantissa(v)) not in (2, 5))
                    else _fmt(v) for v in values]
        return [_fmt(v) if _is_decade(v) else "" for v in values]


def _is_decade(v: float) -> bool:
    return abs(v - round(v)) < 1e-6


def _mantissa(v: float) -> float:
    return 10.0 ** (v - math.floor(v + 1e-9))


def _fmt(v: float) -> str:
    x = 10.0 ** v
    return f"{x:g}" if 1e-3 <= x < 1e5 else f"{x:.0e}".replace("e-0", "e-").replace("e+0", "e")


class FitPanel(QWidget):
    """``set_fit(t, h, rig, result)`` shows a SweepResult; ``best_name()`` and the table for tests."""

    shown = Signal(str)  # best model name, once the model curves are in

    def __init__(self, parent=None, title: str = "Model selection by AIC"):
        super().__init__(parent)
        self.result = None
        self.data: dict | None = None
        self.title = ""
        self._serial = 0
        self._checked: set[str] = set()
        self._updating = False
        self._stale = False  # a result not drawn yet (the panel was hidden)
        self._curves_for = None  # (t, h, rig, result) whose model curves are still to compute
        self.renders = 0

        lay = QVBoxLayout(self)
        lay.setContentsMargins(2, 2, 2, 2)
        self.header = QLabel(title)
        self.header.setWordWrap(True)
        f = self.header.font()
        f.setBold(True)
        self.header.setFont(f)
        lay.addWidget(self.header)
        self.warnings = QLabel("")  # the fit's warnings: the best model does not describe the record, ...
        self.warnings.setWordWrap(True)
        self.warnings.setStyleSheet("background:#fde2e1; color:#6b0d0a; padding:2px;")
        self.warnings.hide()
        lay.addWidget(self.warnings)

        self.table = QTableWidget(0, len(COLUMNS))
        self.table.setHorizontalHeaderLabels(COLUMNS)
        self.table.verticalHeader().setVisible(False)
        self.table.setEditTriggers(QAbstractItemView.NoEditTriggers)
        self.table.setSelectionBehavior(QAbstractItemView.SelectRows)
        self.table.setWordWrap(False)
        hh = self.table.horizontalHeader()
        hh.setSectionResizeMode(QHeaderView.ResizeToContents)
        hh.setSectionResizeMode(COLUMNS.index("notes"), QHeaderView.Stretch)
        self.table.verticalHeader().setDefaultSectionSize(ROW_H)
        self.table.verticalHeader().setMinimumSectionSize(ROW_H)
        self.table.itemChanged.connect(self._item_changed)
        # the result first: the fit's Headline (best model, support, a ± SE, every element's E, η, τ, J ± SE,
        # the noise ratio) beside the model table, in the panel itself
        self.summary = QLabel("")
        self.summary.setTextFormat(Qt.RichText)
        self.summary.setWordWrap(True)  # the words wrap in their cell; the element cells do not (nowrap)
        self.summary.setAlignment(Qt.AlignLeft | Qt.AlignTop)
        self.summary.setTextInteractionFlags(Qt.TextSelectableByMouse)
        self.summary.setStyleSheet("background:#f4f8f1; border:1px solid #cfdcc8; padding:3px;")
        self.summary.setSizePolicy(QSizePolicy.Expanding, QSizePolicy.Minimum)
        self.summary.hide()
        lay.addWidget(self.summary)
        lay.addWidget(self.table)  # as tall as its rows (_fit_table_height): every model shows

        self.plots = pg.GraphicsLayoutWidget()
        lay.addWidget(self.plots, 1)
        self.p_head = self.plots.addPlot(row=0, col=0, title="measured and fitted head")
        self.p_aic = self.plots.addPlot(row=0, col=1, rowspan=2, title="ΔAIC against m")
        self.p_creep = self.plots.addPlot(row=0, col=2, rowspan=2, title="creep J(t) − J₀, best ± 95 %",
                                          axisItems={"left": DecadeAxis("left"), "bottom": DecadeAxis("bottom")})
        self.p_phi = self.plots.addPlot(row=0, col=3, rowspan=2, title="|φ(ω)|",
                                        axisItems={"left": DecadeAxis("left"), "bottom": DecadeAxis("bottom")})
        self.p_res = self.plots.addPlot(row=1, col=0, title="residuals of the best model, ± the record's noise")
        self.p_res.setXLink(self.p_head)
        lay_ = self.plots.ci.layout
        for col, stretch in enumerate((2, 1, 1, 1)):
            lay_.setColumnStretchFactor(col, stretch)
        lay_.setRowStretchFactor(0, 2)
        lay_.setRowStretchFactor(1, 1)
        self.p_head.setLabel("bottom", "time from trigger", units="s")
        self.p_head.setLabel("left", "head − steady", units="m")
        self.p_res.setLabel("left", "h − model", units="m")
        self.p_aic.setLabel("bottom", "m (Kelvin-Voigt elements)")
        self.p_aic.setLabel("left", "log10(1 + ΔAIC)")
        self.p_creep.setLabel("bottom", "t (s)")
        self.p_creep.setLabel("left", "J(t) − J₀ (1/Pa)")
        self.p_creep.setLogMode(x=True, y=True)
        self.p_phi.setLabel("bottom", "f (Hz)")
        self.p_phi.setLabel("left", "|φ|")
        self.p_phi.setLogMode(x=True, y=True)
        for p in (self.p_head, self.p_aic, self.p_creep, self.p_phi, self.p_res):
            p.showGrid(x=True, y=True, alpha=0.25)
            p.getAxis("left").setWidth(52)
        for p in (self.p_creep, self.p_phi):
            for ax in ("left", "bottom"):
                p.getAxis(ax).enableAutoSIPrefix(False)
        for p in (self.p_head, self.p_res):
            p.setClipToView(True)
            p.setDownsampling(auto=True, mode="peak")
        self.head_legend = self.p_head.addLegend(offset=(-5, 5), labelTextSize="8pt")
        self.creep_legend = self.p_creep.addLegend(offset=(5, 5), labelTextSize="7pt", colCount=3)
        self._fit_table_height(7)

    # ------------------------------------------------------------------ API
    def clear(self, text: str = "") -> None:
        self.result = None
        self.data = None
        self._stale = False
        self._curves_for = None
        self._serial += 1
        self.table.setRowCount(0)
        self.warnings.hide()
        self.summary.hide()
        for p in (self.p_head, self.p_aic, self.p_creep, self.p_phi, self.p_res):
            p.clear()
        self.creep_legend.clear()
        self.head_legend.clear()
        if text:
            self.header.setText(text)

    def set_fit(self, t, h, rig, result, title: str = "", compute_async: bool = True) -> None:
        """Show ``result``. Drawn when the panel is on screen; its model curves are computed then, on a
        worker thread (model evaluation during a run would compete with the engine for the GIL)."""
        self.result = result
        self.data = None
        self.title = title
        self._serial += 1
        best = result.best
        self._checked = {best.name}
        others = sorted((f for f in result.models if f is not best and not f.reduced), key=lambda f: f.delta_aic)
        if others:
            self._checked.add(others[0].name)
        self._stale = True
        self._curves_for = (t, h, rig, result)
        if not compute_async:
            self._curves_for = None
            self._curves_ready(fit_view_data(t, h, rig, result), self._serial)
        if self.isVisible():
            self._render()

    def _compute_curves(self) -> None:
        """The model curves of the shown result, on a worker thread (once per result)."""
        if self._curves_for is None:
            return
        args, self._curves_for = self._curves_for, None
        serial = self._serial
        tasks.submit(fit_view_data, *args, owner=self, on_done=lambda d, s=serial: self._curves_ready(d, s),
                     on_error=lambda e: None)

    def ensure_rendered(self) -> None:
        """Draw a result that arrived while the panel was hidden (tests, screenshots)."""
        if self._stale:
            self._render()
        self._compute_curves()

    def best_name(self) -> str | None:
        self.ensure_rendered()
        for r in range(self.table.rowCount()):
            if self.table.item(r, 1).font().bold():
                return self.table.item(r, 1).text()
        return None

    def model_names(self) -> list[str]:
        self.ensure_rendered()
        return [self.table.item(r, 1).text() for r in range(self.table.rowCount())]

    def notes(self) -> dict[str, str]:
        self.ensure_rendered()
        return {self.table.item(r, 1).text(): self.table.item(r, COLUMNS.index("notes")).text()
                for r in range(self.table.rowCount())}

    def set_checked(self, names) -> None:
        self._checked = set(names)
        self._updating = True
        for r in range(self.table.rowCount()):
            it = self.table.item(r, 0)
            it.setCheckState(Qt.Checked if self.table.item(r, 1).text() in self._checked else Qt.Unchecked)
        self._updating = False
        self._draw_head()

    def _fit_label_heights(self) -> None:
        """The wrapped labels (header, warnings, summary) as tall as their text needs at the panel's width: left
        to Qt, a wrapped label's minimum is its height at its narrowest, which made the window taller than
        the screen (the Messages dock pushed off a 1366 x 768 screen)."""
        width = max(self.width(), 600) - 8
        for lab in (self.header, self.warnings, self.summary):
            lab.setMinimumHeight(max(1, lab.heightForWidth(width)))

    def resizeEvent(self, event) -> None:
        super().resizeEvent(event)
        self._fit_label_heights()

    def showEvent(self, event) -> None:
        super().showEvent(event)
        if self._stale:
            self._render()

    # ------------------------------------------------------------------ drawing
    def _render(self) -> None:
        result = self.result
        self._stale = False
        if result is None:
            return
        self.renders += 1
        best = result.best
        doc_sel = criterion({"selection": getattr(result, "selection", None)})
        self.header.setText(
            (self.title + ": " if self.title else "")
            + f"best by minimum {doc_sel}; n = {result.n}, window {result.window_s:g} s, method {result.method}. "
            f"Residual lag-1 autocorrelation {best.lag1_autocorr:.2f}"
            + (" (correlated: the white-noise AIC over-rewards extra parameters)"
               if abs(best.lag1_autocorr) > 0.2 and doc_sel == "AIC" else "")
        )
        summary = summary_html(result, warnings=False)
        self.summary.setText(summary or "")
        self.summary.setVisible(bool(summary))
        text = warnings_text(result)
        self.warnings.setText("⚠ " + text.replace("\n", "\n⚠ ") if text else "")
        self.warnings.setVisible(bool(text))
        self._fit_label_heights()
        self._fill_table(result)
        self._compute_curves()
        # the plots in the next turns of the event loop: drawing everything at once held the GUI
        # thread for 80-100 ms; in three parts no part holds it for more than about 30 ms
        serial = self._serial
        QTimer.singleShot(0, lambda: self._later(serial, "plots"))
        QTimer.singleShot(0, lambda: self._later(serial, "curves"))

    def _later(self, serial: int, what: str) -> None:
        if serial != self._serial or not shiboken6.isValid(self) or self.result is None:
            return  # a newer result, or the panel is gone
        if what == "plots":
            self._draw_result_plots(self.result)
        elif self.data is not None:
            self._draw_curves()

    def _fit_table_height(self, rows: int) -> None:
        """The table is exactly as tall as its rows (all of EL..S6, and reduced ones if shown)."""
        h = self.table.horizontalHeader().sizeHint().height() + rows * ROW_H + 2 * self.table.frameWidth() + 2
        self.table.setMinimumHeight(h)
        self.table.setMaximumHeight(h)

    def _fill_table(self, result) -> None:
        self._updating = True
        rows = model_rows(result)
        self.table.setRowCount(len(rows))
        self.table.horizontalHeaderItem(COLUMNS.index("AIC")).setText(criterion(result.to_dict()))
        bold = QFont(self.table.font())
        bold.setBold(True)
        for r, row in enumerate(rows):
            for c, v in enumerate(row.cells):
                it = QTableWidgetItem(v)
                if c == 0:
                    it.setFlags(Qt.ItemIsUserCheckable | Qt.ItemIsEnabled | Qt.ItemIsSelectable)
                    it.setCheckState(Qt.Checked if row.name in self._checked else Qt.Unchecked)
                    it.setToolTip("show this model in the head plot")
                elif c == 1:
                    it.setForeground(QBrush(QColor(self._color(row.name))))
                    if row.tooltip:
                        it.setToolTip(row.tooltip)
                elif COLUMNS[c] == "notes":
                    it.setToolTip("\n".join(row.notes))
                elif c >= 2 and COLUMNS[c] != "support":
                    it.setTextAlignment(Qt.AlignRight | Qt.AlignVCenter)
                if row.best:
                    it.setBackground(QBrush(BEST_BG))
                    it.setFont(bold)
                    if c == 1:
                        it.setToolTip("best model: minimum of the criterion\n" + row.tooltip)
                self.table.setItem(r, c, it)
        self._fit_table_height(len(rows))
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
        for level, style, where in ((2, Qt.DotLine, 0.3), (10, Qt.DashLine, 0.7)):
            self.p_aic.addItem(pg.InfiniteLine(pos=np.log10(1 + level), angle=0,
                                               pen=pg.mkPen("#999", style=style),
                                               label=f"ΔAIC = {level}", labelOpts={"position": where, "color": "#777"}))

    def _draw_creep(self) -> None:
        """J(t) - J0 of every full model; the best one thick, over its 95 % band; where the choice of model is
        uncertain, the model-averaged band dashed grey (its band holds the models' spread)."""
        self.p_creep.clear()
        self.creep_legend.clear()
        if not self.data or self.result is None:
            return
        best = self.result.best.name
        curves = self.data.get("creep") or {}
        for name in sorted(curves, key=lambda n: n == best):  # the best one drawn last, on top
            c = curves[name]
            ok = np.isfinite(c.J_per_pa) & (c.J_per_pa > 0)
            if not ok.any():
                continue
            color = self._color(name)
            if name == best and c.has_band:
                lo = self.p_creep.plot(c.t_s, c.lower, pen=pg.mkPen(color, width=1, style=Qt.DotLine))
                hi = self.p_creep.plot(c.t_s, c.upper, pen=pg.mkPen(color, width=1, style=Qt.DotLine))
                fill = QColor(color)
                fill.setAlpha(60)
                self.p_creep.addItem(pg.FillBetweenItem(lo, hi, brush=pg.mkBrush(fill)))
            self.p_creep.plot(c.t_s[ok], c.J_per_pa[ok], pen=pg.mkPen(color, width=2.5 if name == best else 1),
                              name=name)
        avg = self.data.get("creep_averaged")
        if avg is not None:
            ok = np.isfinite(avg.lower) & (avg.lower > 0)
            pen = pg.mkPen((90, 90, 90), width=1.2, style=Qt.DashLine)
            self.p_creep.plot(avg.t_s[ok], avg.lower[ok], pen=pen, name=AVERAGED_LABEL)
            self.p_creep.plot(avg.t_s[ok], avg.upper[ok], pen=pen)

    def _curves_ready(self, data: dict, serial: int) -> None:
        if serial != self._serial:
            return  # a newer result replaced this one
        self.data = data
        if self.isVisible() and not self._stale:
            self._draw_curves()
        else:
            self._stale = True  # drawn when the panel is shown
        self.shown.emit(self.result.best.name if self.result else "")

    def warning_text(self) -> str:
        """The warnings line as shown ("" when the fit has none)."""
        self.ensure_rendered()
        return self.warnings.text() if not self.warnings.isHidden() else ""

    def _draw_residuals(self) -> None:
        self.p_res.clear()
        d, result = self.data, self.result
        if not d or result is None or not len(d.get("res", ())):
            return
        sd = getattr(result, "baseline_noise_m", None)
        if sd is not None:  # the record's own noise: where a model that describes it leaves its residuals
            t0, t1 = float(d["res_t"][0]), float(d["res_t"][-1])
            lo = self.p_res.plot([t0, t1], [-sd, -sd], pen=pg.mkPen("#2a9d2a", width=1))
            hi = self.p_res.plot([t0, t1], [sd, sd], pen=pg.mkPen("#2a9d2a", width=1))
            self.p_res.addItem(pg.FillBetweenItem(lo, hi, brush=pg.mkBrush(42, 157, 42, 60)))
        self.p_res.plot(d["res_t"], d["res"], pen=pg.mkPen("#444", width=1))
        ratio = getattr(result.best, "noise_ratio", None)
        self.p_res.setTitle(f"residuals of {result.best.name}" + (f", F/noise {ratio:.3g}" if ratio is not None else "")
                            + (f", ± noise {sd:.3g} m" if sd is not None else ", no baseline noise"))

    def _draw_curves(self) -> None:
        self._draw_head()
        self._draw_residuals()
        self._draw_creep()
        self.p_phi.clear()
        for name, ph in self.data["phi"].items():
            best = self.result is not None and name == self.result.best.name
            self.p_phi.plot(self.data["freq_hz"], ph, pen=pg.mkPen(self._color(name), width=2 if best else 1))

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
