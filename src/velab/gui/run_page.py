"""The Run page: the banner, the control bar (buttons and phase), the devices, the run form and the
live plot. It only draws: the window wires it to the controller (main_window.py)."""

from __future__ import annotations

import numpy as np
from PySide6.QtCore import Qt
from PySide6.QtWidgets import QGroupBox, QLabel, QScrollArea, QSplitter, QVBoxLayout, QWidget

from velab.gui.devices import DevicePanel
from velab.gui.live_plot import LivePlot
from velab.gui.messages import Banner
from velab.gui.run_controls import RunControls
from velab.gui.run_panel import RunPanel


class RunPage(QWidget):
    def __init__(self, qsettings, rig=None, parent=None):
        super().__init__(parent)
        rl = QVBoxLayout(self)
        rl.setContentsMargins(4, 4, 4, 4)
        self.banner = Banner()
        rl.addWidget(self.banner)
        self.controls = RunControls()
        rl.addWidget(self.controls)
        self.form = RunPanel(qsettings, rig=rig)
        # the interlock's verdict on the form (within limits / REFUSED) under the control bar, whole and outside
        # any scroll area: at 1366 x 768 it was cut at the form's foot even scrolled
        self.interlock = self.form.prediction
        rl.addWidget(self.interlock)
        self.split = QSplitter(Qt.Horizontal)
        rl.addWidget(self.split, 1)
        left = QWidget()
        ll = QVBoxLayout(left)
        ll.setContentsMargins(0, 0, 0, 0)
        dev_box = QGroupBox("Devices")
        dl = QVBoxLayout(dev_box)
        dl.setContentsMargins(4, 4, 4, 4)
        self.devices = DevicePanel()
        dl.addWidget(self.devices)
        ll.addWidget(dev_box)
        ll.addWidget(self.form)
        self.scroll = QScrollArea()  # only the form scrolls; the run's buttons are in the control bar
        self.scroll.setWidgetResizable(True)
        self.scroll.setWidget(left)
        self.scroll.setMinimumWidth(300)
        self.scroll.setHorizontalScrollBarPolicy(Qt.ScrollBarAlwaysOff)
        self.split.addWidget(self.scroll)
        right = QWidget()
        rr = QVBoxLayout(right)
        rr.setContentsMargins(0, 0, 0, 0)
        self.live = LivePlot()
        rr.addWidget(self.live, 1)
        self.stats = QLabel("No run yet.")
        rr.addWidget(self.stats)
        self.split.addWidget(right)
        self.split.setStretchFactor(0, 0)
        self.split.setStretchFactor(1, 1)
        self.split.setSizes([370, 900])

    def show_stats(self, rate_hz: float) -> None:
        """The line under the plot: samples, time, head now and its maximum, lost samples."""
        b = self.live.buffer
        if not b.n:
            return
        head = b.column("head_m")
        t = b.column("time_s")[-1] - self.live.offset_s
        with np.errstate(invalid="ignore"):
            peak = np.nanmax(head) if np.isfinite(head).any() else float("nan")
        self.stats.setText(f"{b.n} samples ({rate_hz:g} Hz), t = {t:.2f} s, head {head[-1]:.2f} m "
                           f"(max {peak:.2f} m), lost {self.live.lost_samples}")
