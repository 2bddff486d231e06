"""Live plot of a recording: head and valve position, scrolling, then the whole run.

Samples arrive in blocks at the full rate (10 kHz and more). They are appended to a
growing buffer (amortised O(1)); the display is refreshed at most ``fps`` times a
second from a min/max (peak) decimation of the visible span to about two points per
pixel, so the cost of a refresh does not grow with the sample rate or the length of
the run. At the end of a run the whole record is handed to pyqtgraph with
``setDownsampling(auto=True, mode="peak")`` and ``setClipToView(True)``, so zooming
into any part of it shows every sample.
"""

from __future__ import annotations

import time

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import Qt
from PySide6.QtWidgets import QVBoxLayout, QWidget


class SampleBuffer:
    """Growable columns of float64: ``append(t, **channels)``; views are slices, not copies."""

    def __init__(self, channels: tuple[str, ...], capacity: int = 1 << 16):
        self.names = ("time_s",) + tuple(channels)
        self._data = {k: np.empty(capacity) for k in self.names}
        self.n = 0

    def clear(self) -> None:
        self.n = 0

    def append(self, time_s, **channels) -> None:
        t = np.asarray(time_s, dtype=float).reshape(-1)
        k = t.size
        if not k:
            return
        need = self.n + k
        cap = self._data["time_s"].size
        if need > cap:
            new = max(need, 2 * cap)
            for name, arr in self._data.items():
                grown = np.empty(new)
                grown[: self.n] = arr[: self.n]
                self._data[name] = grown
        self._data["time_s"][self.n:need] = t
        for name in self.names[1:]:
            v = channels.get(name)
            if v is None:
                self._data[name][self.n:need] = np.nan
            else:
                self._data[name][self.n:need] = np.broadcast_to(np.asarray(v, dtype=float).reshape(-1), (k,))
        self.n = need

    def column(self, name: str) -> np.ndarray:
        return self._data[name][: self.n]

    def span(self, t0: float) -> slice:
        """Samples with time >= t0 (times are increasing)."""
        i = int(np.searchsorted(self.column("time_s"), t0))
        return slice(i, self.n)


def peak_decimate(t: np.ndarray, y: np.ndarray, max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Min/max per bucket: at most ``max_points`` points, peaks kept (NaN-safe)."""
    n = t.size
    if n <= max_points:
        return t, y
    buckets = max(1, max_points // 2)
    per = int(np.ceil(n / buckets))
    m = (n // per) * per
    yy = y[:m].reshape(-1, per)
    tt = t[:m].reshape(-1, per)
    with np.errstate(invalid="ignore"):
        lo = np.nanmin(yy, axis=1) if np.isnan(yy).any() else yy.min(axis=1)
        hi = np.nanmax(yy, axis=1) if np.isnan(yy).any() else yy.max(axis=1)
    tout = np.empty(2 * lo.size)
    yout = np.empty(2 * lo.size)
    tout[0::2] = tt[:, 0]
    tout[1::2] = tt[:, -1]
    yout[0::2] = lo
    yout[1::2] = hi
    if m < n:  # the tail
        tout = np.concatenate([tout, t[m:][[0, -1]]])
        yout = np.concatenate([yout, [np.nanmin(y[m:]), np.nanmax(y[m:])]])
    return tout, yout


class LivePlot(QWidget):
    """Head (m) and valve position (%) against time from the trigger (s), x-linked."""

    CHANNELS = ("head_m", "valve_position")

    def __init__(self, parent=None, *, window_s: float = 10.0, fps: float = 10.0):
        super().__init__(parent)
        self.window_s = window_s
        self.min_interval_s = 1.0 / fps
        self.buffer = SampleBuffer(self.CHANNELS)
        self.trigger_time_s: float | None = None
        self.mode = "scroll"  # or "whole"
        self.samples_received = 0
        self.lost_samples = 0
        self.redraws = 0
        self._dirty = False
        self._last_draw = 0.0

        lay = QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        self.view = pg.GraphicsLayoutWidget()
        lay.addWidget(self.view)
        self.head_plot = self.view.addPlot(row=0, col=0)
        self.valve_plot = self.view.addPlot(row=1, col=0)
        self.view.ci.layout.setRowStretchFactor(0, 3)
        self.view.ci.layout.setRowStretchFactor(1, 2)
        self.valve_plot.setXLink(self.head_plot)
        self.head_plot.setLabel("left", "head", units="m")
        self.head_plot.setTitle("pressure head at the valve")
        self.valve_plot.setLabel("left", "valve position", units="%")
        self.valve_plot.setLabel("bottom", "time from trigger", units="s")
        self.valve_plot.setYRange(-5, 105)
        for p in (self.head_plot, self.valve_plot):
            p.showGrid(x=True, y=True, alpha=0.25)
            p.setClipToView(True)
            p.setDownsampling(auto=True, mode="peak")
            p.getAxis("left").setWidth(60)
        self.head_curve = self.head_plot.plot(pen=pg.mkPen("#1f4e9c", width=1))
        self.valve_curve = self.valve_plot.plot(pen=pg.mkPen("#b3541e", width=1.5))
        self.trigger_lines = []
        for p in (self.head_plot, self.valve_plot):
            line = pg.InfiniteLine(angle=90, pen=pg.mkPen("#c00", width=1, style=Qt.DashLine),
                                   label="trigger" if p is self.head_plot else None,
                                   labelOpts={"position": 0.92, "color": "#c00"})
            line.hide()
            p.addItem(line)
            self.trigger_lines.append(line)

    # ------------------------------------------------------------------ data
    def clear(self) -> None:
        self.buffer.clear()
        self.samples_received = 0
        self.lost_samples = 0
        self.trigger_time_s = None
        self.mode = "scroll"
        for line in self.trigger_lines:
            line.hide()
        self.head_curve.setData([], [])
        self.valve_curve.setData([], [])
        self.head_plot.enableAutoRange()
        self._dirty = False

    def append(self, time_s, head_m, valve_position=None, lost: int = 0) -> None:
        """A block of samples (time from the trigger, or from the start before the trigger is known)."""
        t = np.asarray(time_s, dtype=float).reshape(-1)
        self.buffer.append(t, head_m=head_m, valve_position=valve_position)
        self.samples_received += t.size
        self.lost_samples += int(lost or 0)
        self._dirty = True

    def set_trigger(self, t_s: float = 0.0) -> None:
        self.trigger_time_s = float(t_s)
        for line in self.trigger_lines:
            line.setValue(self.trigger_time_s)
            line.show()

    # ------------------------------------------------------------------ drawing
    def refresh(self, force: bool = False) -> bool:
        """Redraw if new data arrived and the last redraw is old enough; True if it drew."""
        now = time.perf_counter()
        if not self._dirty or (not force and now - self._last_draw < self.min_interval_s):
            return False
        self._last_draw = now
        self._dirty = False
        self.redraws += 1
        if self.buffer.n == 0:
            return True
        if self.mode == "whole":
            self._draw_whole()
            return True
        t_all = self.buffer.column("time_s")
        t_end = t_all[-1]
        sl = self.buffer.span(t_end - self.window_s)
        t = t_all[sl]
        width = max(200, int(self.head_plot.vb.width()) or 800)
        for curve, name in ((self.head_curve, "head_m"), (self.valve_curve, "valve_position")):
            td, yd = peak_decimate(t, self.buffer.column(name)[sl], 2 * width)
            curve.setData(td, yd)
        self.head_plot.setXRange(t_end - self.window_s, t_end, padding=0)
        return True

    def show_whole(self) -> None:
        """The whole run, every sample reachable by zooming (pyqtgraph peak downsampling)."""
        self.mode = "whole"
        self._dirty = True
        self.refresh(force=True)

    def _draw_whole(self) -> None:
        t = self.buffer.column("time_s").copy()
        self.head_curve.setData(t, self.buffer.column("head_m").copy(), connect="finite")
        self.valve_curve.setData(t, self.buffer.column("valve_position").copy(), connect="finite")
        self.head_plot.enableAutoRange(x=True, y=True)
        self.valve_plot.enableAutoRange(x=False, y=False)

    def set_run(self, time_s, head_m, valve_position=None, trigger_s: float = 0.0) -> None:
        """Show an archived run whole."""
        self.clear()
        self.append(time_s, head_m, valve_position)
        self.set_trigger(trigger_s)
        self.show_whole()
