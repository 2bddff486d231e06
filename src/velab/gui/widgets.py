"""Value fields that ignore the mouse wheel unless they have the keyboard focus.

Scrolling a page over the beta field must not change the manoeuvre: the wheel over an
unfocused field goes on to its parent (a scroll area scrolls), and the wheel does not give
the field the focus either (StrongFocus). Only ``wheelEvent`` is overridden, so Qt calls into
Python for wheel events alone (an event filter would be called for every event of every
field, each call a wait for the GIL while the engine runs).
"""

from __future__ import annotations

from PySide6.QtCore import Qt
from PySide6.QtWidgets import QComboBox, QDoubleSpinBox, QSpinBox


class _WheelOnlyWhenFocused:
    """Mixed in before the Qt field class: StrongFocus, and the wheel goes to the parent unless focused."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.setFocusPolicy(Qt.StrongFocus)

    def wheelEvent(self, event) -> None:
        if self.hasFocus():
            super().wheelEvent(event)
        else:
            event.ignore()


class DoubleSpinBox(_WheelOnlyWhenFocused, QDoubleSpinBox):
    pass


class SpinBox(_WheelOnlyWhenFocused, QSpinBox):
    pass


class ComboBox(_WheelOnlyWhenFocused, QComboBox):
    pass
