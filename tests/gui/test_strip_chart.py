"""velab.gui.strip_chart: the live view's curves, drawn with a 1 px aliased pen on pixel centres."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pyqtgraph")

from PySide6.QtGui import QColor  # noqa: E402

from velab.gui.live_plot import peak_decimate  # noqa: E402
from velab.gui.strip_chart import Panel, StripChart  # noqa: E402

pytestmark = pytest.mark.gui

HEAD, POSITION = "#1f4e9c", "#b3541e"


def _columns_without(img, rect, color: str) -> list[int]:
    """The pixel columns of ``rect`` (its borders left out) where no pixel has exactly ``color``."""
    want = QColor(color).rgb()
    missing = []
    for x in range(int(rect.left()) + 2, int(rect.right()) - 2):
        if not any(img.pixel(x, y) == want for y in range(int(rect.top()), int(rect.bottom()))):
            missing.append(x)
    return missing


@pytest.mark.parametrize("width", [980, 1366])
def test_curves_have_no_gaps(qtbot, width):
    """A head trace and a valve position whose flat start is a near-horizontal line at a fractional pixel
    height: every column of each panel shows its curve. (Between fractional points a 1 px aliased line
    dropped short near-horizontal segments: three columns of the position's flat start were empty before
    the points were put on pixel centres.)"""
    rng = np.random.default_rng(0)
    t = np.arange(-2000, 6000) / 1000.0
    head = 30.0 + np.where(t < 0, 0.0, 18.0 * np.sign(np.sin(2 * np.pi * t / 0.47)) * np.exp(-t / 3.0))
    head += rng.normal(0.0, 0.1, t.size)
    position = 100.0 / (1.0 + np.exp(32.0 * t - 5.5))
    chart = StripChart([Panel("head", "m", HEAD, (5.0, 55.0)), Panel("valve position", "%", POSITION, (-5.0, 105.0))])
    qtbot.addWidget(chart)
    chart.resize(width, 520)
    chart.set_x_range(-2.0, 6.0)
    for i, y in enumerate((head, position)):
        chart.set_data(i, *peak_decimate(t, y, 2 * width))
    img = chart.grab().toImage()
    for rect, color in zip(chart.panel_rects(), (HEAD, POSITION)):
        assert _columns_without(img, rect, color) == [], color
