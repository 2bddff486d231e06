"""Device panel: each device's connection state, its live values with units, quality and faults."""

from __future__ import annotations

import math
import time

from PySide6.QtCore import Qt
from PySide6.QtGui import QBrush, QColor
from PySide6.QtWidgets import (QAbstractItemView, QHeaderView, QLabel, QTableWidget, QTableWidgetItem, QVBoxLayout,
                               QWidget)

COLUMNS = ("signal", "value", "units", "quality", "age")
OK = QColor("#d8f0d2")
WARN = QColor("#fff0c2")
BAD = QColor("#f9d0cd")
IDLE = QColor("#eeeeee")


def _quality_text(q) -> str:
    return str(getattr(q, "value", q) or "ok")


# each signal as the rig's people read it: (label, units shown, scale from the reading's units, decimals)
SIGNALS = {
    "head": ("head at the valve", "m", {"m": 1.0}, 2),
    "flow": ("flow", "l/s", {"m3/s": 1e3, "l/s": 1.0}, 3),
    "valve_position": ("valve position", "%", {"%": 1.0}, 1),
}


def shown(name: str, value, units: str) -> tuple[str, str, str]:
    """(label, value text, units) of a reading in the rig's units with the digits it deserves: the head
    in m to the cm, the flow in l/s to the ml/s, the valve in % to 0.1 % (a closed valve's 7.6e-08 % is
    0.0 %); a signal not listed keeps its units, 4 significant digits."""
    label, unit, scales, decimals = SIGNALS.get(name, (name, units, {units: 1.0}, None))
    scale = scales.get(units)
    if scale is None:  # units this table does not know: as the device gave them
        unit, scale, decimals = units, 1.0, None
    try:
        v = float(value) * scale
    except (TypeError, ValueError):
        return label, str(value), unit
    if not math.isfinite(v):
        return label, "—", unit
    if decimals is None:
        return label, f"{v:.4g}", unit
    text = f"{v:.{decimals}f}"
    return label, ("0." + "0" * decimals if text.lstrip("-") == "0." + "0" * decimals else text), unit


class DevicePanel(QWidget):
    """``update_status(list)`` from connect(); ``update_readings(dict)`` from "device" events; ``set_fault``.

    (Connect is in the run's control bar, run_controls.py.)"""

    def __init__(self, parent=None):
        super().__init__(parent)
        lay = QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        self.state_label = QLabel("Devices: not connected")
        self.state_label.setWordWrap(True)
        lay.addWidget(self.state_label)
        self.table = QTableWidget(0, len(COLUMNS))
        self.table.setHorizontalHeaderLabels(COLUMNS)
        self.table.verticalHeader().setVisible(False)
        self.table.setEditTriggers(QAbstractItemView.NoEditTriggers)
        self.table.setSelectionMode(QAbstractItemView.NoSelection)
        self.table.horizontalHeader().setSectionResizeMode(QHeaderView.ResizeToContents)
        self.table.horizontalHeader().setSectionResizeMode(0, QHeaderView.Stretch)
        self.table.setHorizontalScrollBarPolicy(Qt.ScrollBarAlwaysOff)
        self.table.verticalHeader().setDefaultSectionSize(20)
        self.table.setMinimumHeight(90)
        self.table.setMaximumHeight(130)
        lay.addWidget(self.table)
        self.devices: dict[str, dict] = {}  # device -> {"state": str, "message": str}
        self.readings: dict[str, object] = {}
        self.faults: dict[str, str] = {}
        self._rows: dict[str, int] = {}

    # ------------------------------------------------------------------ state
    def update_status(self, statuses) -> None:
        """A list of DeviceStatus-like objects (name, connected/state, message) or a name->status dict."""
        items = statuses.items() if isinstance(statuses, dict) else ((None, s) for s in (statuses or []))
        for key, s in items:
            name = key or getattr(s, "name", None) or str(s)
            state = getattr(s, "state", None)
            if state is None:
                connected = getattr(s, "connected", getattr(s, "ok", None))
                state = "connected" if connected else ("not connected" if connected is not None else "unknown")
            msg = getattr(s, "message", "") or getattr(s, "error", "") or ""
            self.devices[name] = {"state": str(getattr(state, "value", state)), "message": str(msg or "")}
            if self.devices[name]["state"] in ("connected", "ok"):
                self.faults.pop(name, None)
        self._summarise()

    def update_valve(self, info: dict) -> None:
        """A ``valve`` event from the engine: the actuator's state and position in the summary line."""
        name = str(info.get("device") or "valve")
        pos = info.get("position_pct")
        # (a measured position's noise around the closed end reads -0.0 at one decimal: shown as 0.0)
        msg = f"{info.get('state', '?')}" + (f", {pos:.1f} % open".replace("-0.0 %", "0.0 %")
                                            if isinstance(pos, (int, float)) else "")
        if info.get("faults"):
            msg += f", faults {', '.join(map(str, info['faults']))}"
        entry = self.devices.setdefault(name, {"state": "connected", "message": ""})
        if entry["message"] != msg:
            entry["message"] = msg
            self._summarise()

    def set_state(self, text: str) -> None:
        self.state_label.setText(text)

    def set_fault(self, device: str, message: str) -> None:
        self.faults[device] = message
        if device in self.devices:
            self.devices[device]["state"] = "fault"
        self._summarise()
        self._redraw_faults()

    def update_readings(self, readings: dict) -> None:
        for name, r in readings.items():
            self.readings[name] = r
            row = self._row(name)
            value = getattr(r, "value", r)
            units = getattr(r, "units", "")
            q = _quality_text(getattr(r, "quality", "ok"))
            ts = getattr(r, "timestamp_s", None)
            age = f"{max(0.0, time.time() - ts):.1f} s" if isinstance(ts, (int, float)) and ts > 1e9 else ""
            label, text, unit = shown(name, value, str(units))
            cells = (label, text, unit, q, age)
            color = OK if q == "ok" else (WARN if q in ("stale", "over_range", "under_range") else BAD)
            if self._device_of(name) in self.faults:
                color = BAD
            for c, text in enumerate(cells):
                it = self.table.item(row, c)
                if it is None:
                    it = QTableWidgetItem()
                    if c == 1:
                        it.setTextAlignment(Qt.AlignRight | Qt.AlignVCenter)
                    self.table.setItem(row, c, it)
                if it.text() != text:
                    it.setText(text)
                if c == 3:
                    it.setBackground(QBrush(color))

    def value(self, name: str):
        r = self.readings.get(name)
        return getattr(r, "value", r)

    # ------------------------------------------------------------------ helpers
    def _device_of(self, signal: str) -> str:
        return signal.split(".", 1)[0] if "." in signal else signal

    def _row(self, name: str) -> int:
        if name not in self._rows:
            self._rows[name] = self.table.rowCount()
            self.table.insertRow(self.table.rowCount())
        return self._rows[name]

    def _redraw_faults(self) -> None:
        for name, row in self._rows.items():
            if self._device_of(name) in self.faults:
                it = self.table.item(row, 3)
                if it is not None:
                    it.setBackground(QBrush(BAD))
                    it.setToolTip(self.faults[self._device_of(name)])

    def _summarise(self) -> None:
        if not self.devices:
            self.state_label.setText("Devices: not connected")
            return
        parts = []
        for name, d in self.devices.items():
            mark = "●" if d["state"] in ("connected", "ok") else "▲"
            parts.append(f"{mark} {name}: {d['state']}" + (f" ({d['message']})" if d["message"] else ""))
        for dev, msg in self.faults.items():
            if dev not in self.devices:
                parts.append(f"▲ {dev}: fault ({msg})")
        self.state_label.setText("\n".join(parts))
