"""How the window tells the operator something: a banner, the status bar and a message log.

User errors (VelabError, SafetyError, device errors) become one readable line; only
unexpected exceptions keep their traceback, and then only in the log's details.
"""

from __future__ import annotations

import datetime as _dt

from PySide6.QtCore import Qt, Signal
from PySide6.QtWidgets import QHBoxLayout, QLabel, QPlainTextEdit, QToolButton, QWidget

from velab.errors import SafetyError, VelabError

LEVELS = ("info", "warning", "error")


def _device_error_types() -> tuple[type, ...]:
    try:
        from velab.drivers.base import DeviceError
    except Exception:  # pragma: no cover - device layer missing
        return ()
    return (DeviceError,)


def describe_error(exc: BaseException) -> tuple[str, str]:
    """(level, one-line message) for an exception raised by a command or a task."""
    if isinstance(exc, SafetyError):
        return "error", f"Refused by the interlock: {exc}"
    if isinstance(exc, VelabError):
        return "error", str(exc)
    if isinstance(exc, _device_error_types()):
        return "error", f"Device error: {exc}"
    if isinstance(exc, TimeoutError):
        return "error", f"Timed out: {exc}" if str(exc) else "Timed out"
    if isinstance(exc, OSError):
        return "error", f"{exc.strerror or type(exc).__name__}: {exc.filename or exc}"
    return "error", f"Internal error ({type(exc).__name__}): {exc}"


_STYLE = {
    "info": "background:#e8f1fb; color:#123; border:1px solid #9bc;",
    "warning": "background:#fff4d6; color:#4a3800; border:1px solid #d9b74a;",
    "error": "background:#fde2e1; color:#6b0d0a; border:1px solid #d66; font-weight:bold;",
}


class Banner(QWidget):
    """A one-line message across the top of a page, until closed or replaced."""

    def __init__(self, parent=None):
        super().__init__(parent)
        lay = QHBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        self.label = QLabel()
        self.label.setWordWrap(True)
        self.label.setTextInteractionFlags(Qt.TextSelectableByMouse)
        self.label.setContentsMargins(8, 4, 8, 4)
        close = QToolButton()
        close.setText("✕")
        close.setAutoRaise(True)
        close.setToolTip("Dismiss")
        close.clicked.connect(self.hide)
        lay.addWidget(self.label, 1)
        lay.addWidget(close)
        self.level = "info"
        self.hide()

    def show_message(self, text: str, level: str = "info") -> None:
        self.level = level
        self.label.setText(text)
        self.label.setStyleSheet(_STYLE.get(level, _STYLE["info"]))
        self.show()

    def text(self) -> str:
        return self.label.text() if self.isVisible() else ""


class MessageLog(QPlainTextEdit):
    """Every message of the session with its time; ``entries`` holds (level, text) for tests."""

    added = Signal(str, str)

    def __init__(self, parent=None):
        super().__init__(parent)
        self.setReadOnly(True)
        self.setMaximumBlockCount(2000)
        self.entries: list[tuple[str, str]] = []

    def add(self, text: str, level: str = "info", details: str = "") -> None:
        self.entries.append((level, text))
        stamp = _dt.datetime.now().strftime("%H:%M:%S")
        tag = {"info": "", "warning": "WARNING ", "error": "ERROR "}.get(level, "")
        self.appendPlainText(f"{stamp}  {tag}{text}")
        if details:
            self.appendPlainText("    " + details.rstrip().replace("\n", "\n    "))
        self.added.emit(level, text)

    def texts(self, level: str | None = None) -> list[str]:
        return [t for lv, t in self.entries if level is None or lv == level]
