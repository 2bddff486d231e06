"""The run's control bar: Connect, Arm, Trigger, Stop, Abort, Reset valve and the phase indicator.

It sits above the Run page's splitter, outside any scroll area, so every control of a run is
on screen at any window size the window allows (1366 x 768 included). ``apply(state)`` sets
each button from a :class:`~velab.gui.state.ControlState` and nothing else; the indicator
shows the engine's phase word (as ``velab record`` prints it) and its countdown.
"""

from __future__ import annotations

from PySide6.QtCore import Signal
from PySide6.QtWidgets import QFrame, QHBoxLayout, QLabel, QPushButton, QSizePolicy, QVBoxLayout, QWidget

from velab.gui.state import BUTTONS, COLORS, ControlState

TIPS = {
    "connect": "open (or reopen) every device of the bench: a new connection",
    "arm": "check the interlock and the steady state, open the run file, record the baseline, arm the actuator "
           "(connects first if needed)",
    "trigger": "start the valve manoeuvre (pressed during the baseline: queued until the baseline is in)",
    "stop": "end the recording normally (the run is kept; fitted if its fit window is in)",
    "abort": "abort: valve to its safe state, run marked aborted",
    "reset_valve": "reset the actuator: reopens a closed valve (clears an actuator FAULT) and lets the flow settle",
}


ABORT_LIVE = ("QPushButton:enabled { color: white; background: #b3261e; font-weight: bold; border: 1px solid #7a1912;"
              " border-radius: 3px; padding: 2px 12px; }")


class RunControls(QFrame):
    """``clicked(action)`` with action in BUTTONS; ``apply(state)``; ``phase_label``, ``detail_label``."""

    clicked = Signal(str)

    def __init__(self, parent=None):
        super().__init__(parent)
        self.setFrameShape(QFrame.StyledPanel)
        lay = QHBoxLayout(self)
        lay.setContentsMargins(6, 4, 6, 4)
        self.buttons: dict[str, QPushButton] = {}
        for name, text in zip(BUTTONS, ("Connect", "Arm", "Trigger", "Stop", "Abort", "Reset valve")):
            b = QPushButton(text)
            b.setToolTip(TIPS[name])
            b.setMinimumHeight(34)
            b.setEnabled(False)
            b.clicked.connect(lambda _=False, n=name: self.clicked.emit(n))
            lay.addWidget(b)
            self.buttons[name] = b
        self.arm_button, self.trigger_button = self.buttons["arm"], self.buttons["trigger"]
        self.stop_button, self.abort_button = self.buttons["stop"], self.buttons["abort"]
        self.connect_button, self.reset_valve_button = self.buttons["connect"], self.buttons["reset_valve"]
        # red only while Abort can act: a disabled Abort is drawn as every disabled button (grey), so the
        # bar never shows a live-looking control that does nothing
        self.abort_button.setStyleSheet(ABORT_LIVE)
        self.trigger_button.setStyleSheet("QPushButton { font-weight: bold; }")
        self.arm_button.setMinimumWidth(120)
        lay.addSpacing(10)
        box = QWidget()
        bl = QVBoxLayout(box)
        bl.setContentsMargins(8, 0, 8, 0)
        bl.setSpacing(0)
        self.phase_label = QLabel("disconnected")
        f = self.phase_label.font()
        f.setPointSizeF(f.pointSizeF() * 1.35)
        f.setBold(True)
        self.phase_label.setFont(f)
        self.detail_label = QLabel("")
        self.detail_label.setWordWrap(True)
        # two lines, always: a longer or shorter countdown text must not re-lay out the page (the
        # live plot below would be resized and redrawn)
        self.detail_label.setFixedHeight(2 * self.detail_label.fontMetrics().lineSpacing() + 2)
        bl.addWidget(self.phase_label)
        bl.addWidget(self.detail_label)
        box.setSizePolicy(QSizePolicy.Expanding, QSizePolicy.Preferred)
        self.indicator = box
        lay.addWidget(box, 1)
        self.state: ControlState | None = None

    def apply(self, state: ControlState) -> None:
        """Enable each button from ``state`` alone; show the phase and its countdown."""
        self.state = state
        for name, on in state.controls().items():
            self.buttons[name].setEnabled(on)
        self.arm_button.setText("Reopen + Arm" if state.reopen_before_arm else "Arm")
        bold = "QPushButton { font-weight: bold; }" if (state.valve_fault or state.reopen_before_arm) else ""
        if self.reset_valve_button.styleSheet() != bold:  # a style sheet change re-polishes the widget
            self.reset_valve_button.setStyleSheet(bold)
        phase, detail = state.indicator()
        self.phase_label.setText(phase)
        self.detail_label.setText(detail)
        style = f"background: {COLORS.get(phase, 'transparent')}; border-radius: 3px;"
        if self.indicator.styleSheet() != style:
            self.indicator.setStyleSheet(style)

    def phase_text(self) -> str:
        return f"{self.phase_label.text()}: {self.detail_label.text()}".rstrip(": ")

    def enabled(self) -> dict[str, bool]:
        return {n: b.isEnabled() for n, b in self.buttons.items()}


def status_text(state: ControlState) -> str:
    """The status bar's short form: phase and the countdown."""
    phase, detail = state.indicator()
    short = detail.split(";")[0].split(" (")[0]
    return f"{phase} — {short}" if short else phase

