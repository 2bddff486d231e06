"""A light strip chart for the live view: stacked panels on one time axis, drawn in one paintEvent.

Why not pyqtgraph while recording: a pyqtgraph frame makes about 70 calls from Qt back into
Python (bounding rects, item paints); each needs the GIL, which the engine, the simulated rig
and the online fit hold most of the time, so each is a wait and a frame took 10-200 ms of the
GUI thread for 4 ms of work (docs/gui.md, "Latency"). Here Qt calls Python once per frame:
``paintEvent`` draws a cached background (grid, ticks, labels, marker: redrawn only when a
range, a label or the size changes) and the curves (QPainterPaths in pixels, rebuilt when the
data, a range or the size changed) with about a dozen QPainter calls (each a chance for another thread to take the GIL). pyqtgraph still shows the whole run afterwards
(zoom, every sample).
"""

from __future__ import annotations

import math

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import QLineF, QPointF, QRectF, Qt, Signal
from PySide6.QtGui import QColor, QFont, QFontMetrics, QPainter, QPainterPath, QPen, QPixmap
from PySide6.QtWidgets import QSizePolicy, QWidget

GRID = QColor("#e6e6e6")  # opaque: blended (alpha) lines cost 10x more to draw
AXIS = QColor("#444")
TRIGGER = QColor("#c00")


def nice_ticks(lo: float, hi: float, target: int = 6) -> tuple[np.ndarray, int]:
    """Round tick positions in [lo, hi] (steps 1, 2, 5 x 10^k) and the decimals to print them."""
    span = hi - lo
    if not (math.isfinite(span) and span > 0):
        return np.array([lo]), 1
    raw = span / max(1, target)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(s * mag for s in (1, 2, 5, 10) if s * mag >= raw)
    ticks = np.arange(math.ceil(lo / step), math.floor(hi / step) + 1) * step
    return ticks, max(0, -int(math.floor(math.log10(step) + 1e-9)))


class Panel:
    """One plot area of the strip chart: a y label with units, a colour, a y range and its data."""

    def __init__(self, label: str, units: str, color: str, y_range=(0.0, 1.0)):
        self.label, self.units = label, units
        # one pixel, aliased: Qt strokes a wider pen through its general stroker, ~10 x the time, and PySide
        # holds the GIL in drawPath (a 1.3 px pen took 6 ms a curve; under CPU contention a frame held the
        # GIL for 0.6 s and the recorder's and the simulated rig's threads waited)
        self.pen = QPen(QColor(color), 1)
        self.y_range = tuple(y_range)
        self.x = self.y = np.empty(0)
        self.path = QPainterPath()  # in pixels, built when the data, a range or the size changed
        self.path_key = None


class StripChart(QWidget):
    """``set_data(i, x, y)``, ``set_x_range``, ``set_y_range(i, lo, hi)``, ``set_marker(x, text)``;
    ``zoom_requested`` when the operator clicks or scrolls on it while ``zoomable``."""

    zoom_requested = Signal()

    LEFT, RIGHT, TOP, BOTTOM, GAP = 66, 12, 24, 42, 14

    def __init__(self, panels: list[Panel], title: str = "", parent=None):
        super().__init__(parent)
        self.panels = panels
        self.title = title
        self.x_range = (0.0, 10.0)
        self.x_label = ""
        self.marker: tuple[float, str] | None = None
        self.zoomable = False
        self.paints = 0
        self._bg: QPixmap | None = None
        self._bg_key = None
        self.setAttribute(Qt.WA_OpaquePaintEvent)  # every pixel is painted: no background erase first
        self.setSizePolicy(QSizePolicy.Expanding, QSizePolicy.Expanding)
        self.setMinimumSize(300, 200)
        self._font = QFont(self.font())
        self._font.setPointSizeF(max(7.0, self._font.pointSizeF() * 0.9))
        self._title_font = QFont(self.font())
        self._title_font.setPointSizeF(self._font.pointSizeF() * 1.25)

    # ------------------------------------------------------------------ data (not in the paint)
    def set_data(self, i: int, x: np.ndarray, y: np.ndarray) -> None:
        """The curve of panel ``i`` (gaps where y is not finite)."""
        pn = self.panels[i]
        pn.x, pn.y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        pn.path_key = None
        self.update()

    def set_x_range(self, lo: float, hi: float) -> None:
        if (float(lo), float(hi)) != self.x_range:
            self.x_range = (float(lo), float(hi))
            self.update()

    def set_y_range(self, i: int, lo: float, hi: float) -> None:
        if (float(lo), float(hi)) != self.panels[i].y_range:
            self.panels[i].y_range = (float(lo), float(hi))
            self.update()

    def set_x_label(self, text: str) -> None:
        if text != self.x_label:
            self.x_label = text
            self.update()

    def set_marker(self, x: float | None, text: str = "") -> None:
        self.marker = None if x is None else (float(x), text)
        self.update()

    def clear(self) -> None:
        for p in self.panels:
            p.x = p.y = np.empty(0)
            p.path_key = None
        self.marker = None
        self.update()

    def mousePressEvent(self, event) -> None:
        if self.zoomable:
            self.zoom_requested.emit()
        super().mousePressEvent(event)

    def wheelEvent(self, event) -> None:
        if self.zoomable:
            self.zoom_requested.emit()
        event.ignore()

    # ------------------------------------------------------------------ geometry
    def panel_rects(self) -> list[QRectF]:
        w, h = self.width(), self.height()
        inner_h = max(20.0, h - self.TOP - self.BOTTOM - self.GAP * (len(self.panels) - 1))
        weights = [3.0, 2.0][: len(self.panels)] + [1.0] * max(0, len(self.panels) - 2)
        total = sum(weights)
        rects, y = [], float(self.TOP)
        for wt in weights:
            ph = inner_h * wt / total
            rects.append(QRectF(self.LEFT, y, max(20.0, w - self.LEFT - self.RIGHT), ph))
            y += ph + self.GAP
        return rects

    # ------------------------------------------------------------------ painting (one Python call a frame)
    def _path(self, panel: Panel, r: QRectF) -> QPainterPath:
        """The panel's curve in pixels (mapped here, not by a painter transform: a raster painter with a
        strongly anisotropic transform dropped segments of near-horizontal lines), each point at the centre
        of its pixel: a 1 px aliased line between fractional points also drops short near-horizontal
        segments (the rasteriser's diamond rule; a valve position's flat start showed gaps)."""
        key = (r.left(), r.top(), r.width(), r.height(), self.x_range, panel.y_range)
        if panel.path_key != key:
            (x0, x1), (y0, y1) = self.x_range, panel.y_range
            if panel.x.size > 1:
                px = r.left() + (panel.x - x0) * (r.width() / (x1 - x0) if x1 > x0 else 1.0)
                py = r.bottom() - (panel.y - y0) * (r.height() / (y1 - y0) if y1 > y0 else 1.0)
                panel.path = pg.arrayToQPath(np.floor(px) + 0.5, np.floor(py) + 0.5, connect="finite")
            else:
                panel.path = QPainterPath()
            panel.path_key = key
        return panel.path

    def paintEvent(self, event) -> None:
        """The cached background (grid, ticks, labels, marker), then each curve: about a dozen Qt calls."""
        self.paints += 1
        rects = self.panel_rects()
        key = (self.width(), self.height(), self.devicePixelRatioF(), self.x_range, self.x_label, self.marker,
               self.title, tuple(pn.y_range for pn in self.panels))
        if key != self._bg_key:
            self._bg = self._background(rects)
            self._bg_key = key
        p = QPainter(self)
        p.drawPixmap(0, 0, self._bg)
        for panel, r in zip(self.panels, rects):
            p.setClipRect(r)
            p.setPen(panel.pen)
            p.drawPath(self._path(panel, r))
        p.end()

    def _background(self, rects: list[QRectF]) -> QPixmap:
        """Everything but the curves, drawn when a range, a label, the marker or the size changes."""
        dpr = self.devicePixelRatioF()
        pm = QPixmap(int(self.width() * dpr), int(self.height() * dpr))
        pm.setDevicePixelRatio(dpr)
        pm.fill(Qt.white)
        p = QPainter(pm)
        p.setFont(self._font)
        fm = QFontMetrics(self._font)
        x0, x1 = self.x_range
        xticks, xdec = nice_ticks(x0, x1, max(2, int(self.width() / 90)))
        if self.title:
            p.setFont(self._title_font)
            p.setPen(AXIS)
            p.drawText(QRectF(self.LEFT, 0, rects[0].width(), self.TOP), Qt.AlignCenter, self.title)
            p.setFont(self._font)
        for k, (panel, r) in enumerate(zip(self.panels, rects)):
            y0, y1 = panel.y_range
            sx = r.width() / (x1 - x0) if x1 > x0 else 1.0
            sy = r.height() / (y1 - y0) if y1 > y0 else 1.0
            yticks, ydec = nice_ticks(y0, y1, max(2, int(r.height() / 40)))
            p.setPen(QPen(GRID, 1))
            lines = [QLineF(px, r.top(), px, r.bottom()) for px in r.left() + (xticks - x0) * sx]
            lines += [QLineF(r.left(), py, r.right(), py) for py in r.bottom() - (yticks - y0) * sy]
            p.drawLines(lines)
            p.setPen(AXIS)
            p.drawRect(r)
            for yv in yticks:
                py = r.bottom() - (yv - y0) * sy
                p.drawText(QRectF(r.left() - 44, py - 8, 40, 16), Qt.AlignRight | Qt.AlignVCenter, f"{yv:.{ydec}f}")
            p.save()
            p.translate(12, r.center().y())
            p.rotate(-90)
            text = f"{panel.label} ({panel.units})" if panel.units else panel.label
            if fm.horizontalAdvance(text) > r.height():  # a short panel: its label's first word, not one
                short = panel.label.split()[0]  # run into the next panel's: "valve (%)", "head (m)"
                text = f"{short} ({panel.units})" if panel.units else short
            p.drawText(QRectF(-r.height() / 2, -10, r.height(), 16), Qt.AlignCenter, text)
            p.restore()
            if self.marker is not None and x0 <= self.marker[0] <= x1:
                px = r.left() + (self.marker[0] - x0) * sx
                p.setPen(QPen(TRIGGER, 1, Qt.DashLine))
                p.drawLine(QPointF(px, r.top()), QPointF(px, r.bottom()))
                if k == 0 and self.marker[1]:
                    p.drawText(QPointF(px + 4, r.top() + fm.ascent() + 2), self.marker[1])
        r = rects[-1]  # the shared time axis under the last panel
        sx = r.width() / (x1 - x0) if x1 > x0 else 1.0
        p.setPen(AXIS)
        for xv in xticks:
            px = r.left() + (xv - x0) * sx
            p.drawText(QRectF(px - 40, r.bottom() + 3, 80, 16), Qt.AlignHCenter | Qt.AlignTop, f"{xv:.{xdec}f}")
        p.drawText(QRectF(r.left(), r.bottom() + 20, r.width(), 18), Qt.AlignHCenter | Qt.AlignTop,
                   f"{self.x_label} (s)" if self.x_label else "s")
        p.end()
        return pm
