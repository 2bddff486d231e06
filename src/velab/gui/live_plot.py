"""Live plot of a recording: head and valve position, paging, then the whole run.

Time axis: the samples arrive on the run file's axis (t = 0 at the *planned* trigger, the
end of the baseline). The plot shows time from the trigger: from the moment the trigger is
commanded, t = 0 is the engine's estimate at the command (said on the axis), then the
instant measured from the valve position as soon as the engine publishes it; before the
trigger, the planned one (said on the axis too).

Cost: samples arrive in blocks at the full rate (10 kHz and more) and are appended to a
growing buffer (amortised O(1)); the display is refreshed at most ``fps`` times a second
from a min/max (peak) decimation of the visible span to about two points per pixel, so a
refresh costs the same at any rate or run length. While recording, the plot is a
:class:`~velab.gui.strip_chart.StripChart` (one Python call per frame: with the GIL shared
with the engine, the simulated rig and the fits, each of pyqtgraph's ~70 calls back into
Python per frame was a wait). The view pages (it moves by a quarter window when the data
reach its right edge) and the head range grows at once and shrinks only when the data use
less than half of it, so the chart's cached background is redrawn a few times per window.
At the end of a run the strip chart shows the whole run; a click on it hands the record to
pyqtgraph with peak downsampling and clip-to-view (zoom to see every sample).
"""

from __future__ import annotations

import math
import time

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import Qt
from PySide6.QtWidgets import QStackedWidget, QVBoxLayout, QWidget

from velab.gui.strip_chart import Panel, StripChart

AXIS_PLANNED = "time from the planned trigger (end of the baseline)"
AXIS_ESTIMATE = "time from the trigger — ESTIMATE at the command (measured instant pending)"
AXIS_MEASURED = "time from the trigger, measured from the valve position"
AXIS_NONE = "time on the run's axis (no trigger)"
AXIS_STORED = "time from the run's trigger instant"


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

    def span(self, t0: float, t1: float | None = None) -> slice:
        """Samples with t0 <= time (< t1) (times are increasing)."""
        t = self.column("time_s")
        i = int(np.searchsorted(t, t0))
        j = self.n if t1 is None else int(np.searchsorted(t, t1))
        return slice(i, j)


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
        if np.isnan(yy).any():
            import warnings

            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN buckets stay NaN (a gap)
                lo, hi = np.nanmin(yy, axis=1), np.nanmax(yy, axis=1)
        else:
            lo, hi = yy.min(axis=1), yy.max(axis=1)
    tout = np.empty(2 * lo.size)
    yout = np.empty(2 * lo.size)
    tout[0::2] = tt[:, 0]
    tout[1::2] = tt[:, -1]
    yout[0::2] = lo
    yout[1::2] = hi
    if m < n:  # the tail
        tail = y[m:]
        fin = tail[np.isfinite(tail)]
        tout = np.concatenate([tout, t[m:][[0, -1]]])
        yout = np.concatenate([yout, [fin.min(), fin.max()] if fin.size else [np.nan, np.nan]])
    return tout, yout


class LivePlot(QWidget):
    """Head (m) and valve position (%) against time from the trigger (s)."""

    CHANNELS = ("head_m", "valve_position")
    PAGE = 0.25  # the view moves by this fraction of the window when the data reach its edge

    def __init__(self, parent=None, *, window_s: float = 10.0, fps: float = 10.0):
        super().__init__(parent)
        self.window_s = window_s
        self.min_interval_s = 1.0 / fps
        self.buffer = SampleBuffer(self.CHANNELS)
        self.trigger_time_s: float | None = None  # on the run file's axis
        self.trigger_measured = False
        self.mode = "scroll"  # or "whole"
        self.samples_received = 0
        self.lost_samples = 0
        self.redraws = 0
        self._dirty = False
        self._last_draw = 0.0
        self._yr: tuple[float, float] | None = None
        self._x0: float | None = None  # left edge of the page (display axis)
        self._archived = False  # an archived run: its stored trigger instant

        lay = QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        self.stack = QStackedWidget()
        lay.addWidget(self.stack)
        self.strip = StripChart([Panel("head", "m", "#1f4e9c", (0.0, 1.0)),
                                 Panel("valve position", "%", "#b3541e", (-5.0, 105.0))],
                                title="pressure head at the valve")
        self.stack.addWidget(self.strip)
        self.strip.zoom_requested.connect(self.show_interactive)
        self.view = pg.GraphicsLayoutWidget()
        self.stack.addWidget(self.view)
        self.head_plot = self.view.addPlot(row=0, col=0)
        self.valve_plot = self.view.addPlot(row=1, col=0)
        self.view.ci.layout.setRowStretchFactor(0, 3)
        self.view.ci.layout.setRowStretchFactor(1, 2)
        self.valve_plot.setXLink(self.head_plot)
        self.head_plot.setLabel("left", "head", units="m")
        self.head_plot.setTitle("pressure head at the valve")
        self.valve_plot.setLabel("left", "valve", units="%")  # short: the panel may be 70 px tall
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
        self._set_axis_label()

    # ------------------------------------------------------------------ data
    def clear(self) -> None:
        self.buffer.clear()
        self.samples_received = 0
        self.lost_samples = 0
        self.trigger_time_s = None
        self.trigger_measured = False
        self.mode = "scroll"
        self._archived = False
        self._yr = self._x0 = None
        for line in self.trigger_lines:
            line.hide()
        self.head_curve.setData([], [])
        self.valve_curve.setData([], [])
        self.strip.clear()
        self.strip.title = "pressure head at the valve"
        self.strip.zoomable = False
        self.stack.setCurrentWidget(self.strip)
        self._set_axis_label()
        self._dirty = False

    def append(self, time_s, head_m, valve_position=None, lost: int = 0) -> None:
        """A block of samples on the run file's axis (t = 0 at the planned trigger)."""
        t = np.asarray(time_s, dtype=float).reshape(-1)
        self.buffer.append(t, head_m=head_m, valve_position=valve_position)
        self.samples_received += t.size
        self.lost_samples += int(lost or 0)
        self._dirty = True

    @property
    def offset_s(self) -> float:
        """Where t = 0 of the display is on the run's axis: the trigger (measured or estimated), else 0."""
        return self.trigger_time_s if self.trigger_time_s is not None else 0.0

    @property
    def axis_label(self) -> str:
        return self.strip.x_label

    def set_trigger(self, t_s: float | None, measured: bool = False) -> None:
        """The trigger instant on the run's axis: the estimate at the command, then the measured one.

        The display's t = 0 moves to it (a measured instant is not replaced by an estimate)."""
        if t_s is None or not math.isfinite(float(t_s)):
            return
        if self.trigger_measured and not measured:
            return
        self.trigger_time_s = float(t_s)
        self.trigger_measured = bool(measured)
        label = "trigger" if measured or self._archived else "trigger (estimate)"
        for line in self.trigger_lines:
            line.setValue(0.0)
            line.show()
        if self.trigger_lines[0].label is not None:
            self.trigger_lines[0].label.setFormat(label)
        self.strip.set_marker(0.0, label)
        self._x0 = None  # page again on the new axis
        self._set_axis_label()
        self._dirty = True
        if self.mode == "whole":
            self.refresh(force=True)

    def _set_axis_label(self) -> None:
        if self.trigger_time_s is None:
            text = AXIS_PLANNED if self.mode == "scroll" else AXIS_NONE
        elif self._archived:
            text = AXIS_STORED
        else:
            text = AXIS_MEASURED if self.trigger_measured else AXIS_ESTIMATE
        self.strip.set_x_label(text)
        if self.valve_plot.getAxis("bottom").labelText != text:
            self.valve_plot.setLabel("bottom", text, units="s")

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
            if self.stack.currentWidget() is self.view:
                self._draw_whole()
            else:
                self.show_whole()
            return True
        off = self.offset_s
        t_all = self.buffer.column("time_s")
        t_first, t_end = t_all[0] - off, t_all[-1] - off
        w = self.window_s
        if self._x0 is None or t_end > self._x0 + w or t_end < self._x0:
            # page: the view moves by a quarter window when the data reach its right edge (the axis and
            # grid are then redrawn a few times per window, not at every frame)
            self._x0 = t_first if t_end - t_first <= w else t_end - (1.0 - self.PAGE) * w
        x0 = self._x0
        sl = self.buffer.span(x0 + off)
        t = t_all[sl] - off
        width = max(200, self.strip.width() - StripChart.LEFT - StripChart.RIGHT)
        for i, name in enumerate(self.CHANNELS):
            td, yd = peak_decimate(t, self.buffer.column(name)[sl], 2 * width)
            self.strip.set_data(i, td, yd)
            if i == 0:
                self._fit_head_range(yd)
        self.strip.set_x_range(x0, x0 + w)
        return True

    def _fit_head_range(self, y: np.ndarray) -> None:
        """Grow the head range at once; shrink it only when the data use less than half of it."""
        fin = y[np.isfinite(y)]
        if not fin.size:
            return
        lo, hi = float(fin.min()), float(fin.max())
        span = max(hi - lo, 1.0)
        if self._yr is not None and self._yr[0] <= lo and hi <= self._yr[1] \
                and span > 0.5 * (self._yr[1] - self._yr[0]) / 1.3:
            return
        self._yr = (lo - 0.15 * span, hi + 0.15 * span)
        self.strip.set_y_range(0, *self._yr)

    def show_whole(self) -> None:
        """The whole run on the strip chart (decimated); a click or the wheel on it opens the interactive
        view (pyqtgraph: zoom to see every sample). The strip chart costs the GUI thread a few ms; the
        interactive view's first layout and paint ~50 ms, so it is built only when asked for."""
        self.mode = "whole"
        self._set_axis_label()
        self._dirty = False
        b = self.buffer
        if b.n == 0:
            return
        off = self.offset_s
        t = b.column("time_s") - off
        width = max(200, self.strip.width() - StripChart.LEFT - StripChart.RIGHT)
        for i, name in enumerate(self.CHANNELS):
            td, yd = peak_decimate(t, b.column(name), 2 * width)
            self.strip.set_data(i, td, yd)
            if i == 0:
                self._yr = None
                self._fit_head_range(yd)
        self.strip.set_x_range(float(t[0]), float(t[-1]) if t[-1] > t[0] else float(t[0]) + 1.0)
        self.strip.title = "pressure head at the valve: the whole run (click to zoom)"
        self.strip.zoomable = True
        self.stack.setCurrentWidget(self.strip)
        self.redraws += 1

    def show_interactive(self) -> None:
        """The whole run in pyqtgraph (peak downsampling, clip to view): zoom and pan to every sample."""
        self.mode = "whole"
        self._set_axis_label()
        self._draw_whole()
        self.stack.setCurrentWidget(self.view)

    def _draw_whole(self) -> None:
        t = self.buffer.column("time_s") - self.offset_s
        self.head_curve.setData(t, self.buffer.column("head_m").copy(), connect="finite")
        self.valve_curve.setData(t, self.buffer.column("valve_position").copy(), connect="finite")
        self.head_plot.enableAutoRange(x=True, y=True)
        self.valve_plot.enableAutoRange(x=False, y=False)

    def set_run(self, time_s, head_m, valve_position=None, trigger_s: float | None = 0.0) -> None:
        """Show an archived run whole (t = 0 at its stored trigger instant)."""
        self.clear()
        self.append(time_s, head_m, valve_position)
        self.mode = "whole"
        self._archived = True
        if trigger_s is not None and math.isfinite(float(trigger_s)):
            self.set_trigger(trigger_s, measured=True)
        self.show_interactive()
