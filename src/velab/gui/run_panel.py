"""The run form: run metadata, manoeuvre and recording parameters, and the interlock's predicted surge.

The buttons that act on a run are in :mod:`velab.gui.run_controls`; the form is disabled while
a run is armed or recording (its settings go with the Arm command)."""

from __future__ import annotations

from PySide6.QtCore import QSettings, Qt, Signal
from PySide6.QtWidgets import (QCheckBox, QFormLayout, QGroupBox, QLabel, QLineEdit,
                               QVBoxLayout, QWidget)

from velab.errors import VelabError
from velab.gui.widgets import ComboBox, DoubleSpinBox
from velab.recording.phases import ACTIVE_PHASES

RATES_HZ = (1000.0, 2000.0, 5000.0, 10000.0)


def _spin(lo, hi, value, decimals=2, suffix="", step=None, special=None) -> DoubleSpinBox:
    s = DoubleSpinBox()
    s.setRange(lo, hi)
    s.setDecimals(decimals)
    s.setValue(value)
    if suffix:
        s.setSuffix(suffix)
    if step:
        s.setSingleStep(step)
    if special:
        s.setSpecialValueText(special)
    s.setKeyboardTracking(False)
    return s


class RunPanel(QWidget):
    """The form; ``settings()`` gives the RecordSettings keyword arguments."""

    changed = Signal()

    def __init__(self, qsettings: QSettings, rig=None, parent=None):
        super().__init__(parent)
        self.qs = qsettings
        self.rig = rig
        lay = QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)

        meta = QGroupBox("Run")
        mf = QFormLayout(meta)
        self.title_edit = QLineEdit()
        self.title_edit.setPlaceholderText("e.g. closure 3, 2 bar")
        self.operator_edit = QLineEdit(qsettings.value("run/operator", ""))
        self.specimen_edit = QLineEdit(qsettings.value("run/specimen", ""))
        self.specimen_edit.setPlaceholderText("pipe or specimen ID")
        self.notes_edit = QLineEdit()
        self.notes_edit.setPlaceholderText("notes stored with the run")
        mf.addRow("title", self.title_edit)
        mf.addRow("operator", self.operator_edit)
        mf.addRow("specimen", self.specimen_edit)
        mf.addRow("notes", self.notes_edit)
        lay.addWidget(meta)

        self.fired_valve = False  # (set_fired_valve: the connected bench's valve is fired by a digital line)
        self._active = False
        man = QGroupBox("Manoeuvre and recording")
        g = QFormLayout(man)
        beta0 = rig.manoeuvre.beta_per_s if rig is not None else 0.0
        gamma0 = rig.manoeuvre.gamma if rig is not None else 0.0
        self.beta_spin = _spin(0, 1000, float(qsettings.value("run/beta_per_s", beta0) or 0), 2, " 1/s", 1,
                               special="rig default")
        self.gamma_spin = _spin(0, 100, float(qsettings.value("run/gamma", gamma0) or 0), 3, "", 0.05,
                                special="rig default")
        self.end_spin = _spin(0, 99, float(qsettings.value("run/end_position_pct", 0.0)), 1, " %", 5)
        self.margin_spin = _spin(0, 500, float(qsettings.value("run/surge_margin_pct", 10.0)), 0, " %", 5)
        self.margin_spin.setToolTip("safety margin added to the Joukowsky surge by the interlock")
        self.duration_spin = _spin(0.5, 600, float(qsettings.value("run/duration_s", 30.0)), 1, " s", 5)
        self.pre_spin = _spin(0.1, 60, float(qsettings.value("run/pretrigger_s", 2.0)), 1, " s", 0.5)
        self.armed_timeout_spin = _spin(0, 3600, float(qsettings.value("run/armed_timeout_s", 0.0)), 0, " s", 10,
                                        special="bench default")
        self.armed_timeout_spin.setToolTip("an armed rig without a trigger disarms itself after this long "
                                           "(bench default: the bench's [recorder] armed_timeout_s, else 300 s)")
        self.rate_combo = ComboBox()
        for r in RATES_HZ:
            self.rate_combo.addItem(f"{r:g} Hz", r)
        rate = float(qsettings.value("run/sample_rate_hz", 1000.0))
        self.rate_combo.setCurrentIndex(max(0, self.rate_combo.findData(rate)))
        self.fit_check = QCheckBox("calibrate EL, S1..S6 after the run")
        self.fit_check.setChecked(qsettings.value("run/fit", "true") in (True, "true"))
        self.models_edit = QLineEdit(qsettings.value("run/fit_models", "0-6"))
        self.models_edit.setToolTip("models to calibrate, by number of Kelvin-Voigt elements (0 = EL): 0-6, 1-4, 1,3")
        self.fit_window_spin = _spin(0.5, 600, float(qsettings.value("run/fit_window_s", 20.0)), 1, " s", 1)
        self.out_edit = QLineEdit(qsettings.value("run/out_dir", "runs"))
        g.addRow("closure rate β", self.beta_spin)
        g.addRow("shape γ", self.gamma_spin)
        g.addRow("end position", self.end_spin)
        g.addRow("surge margin", self.margin_spin)
        g.addRow("duration", self.duration_spin)
        g.addRow("pre-trigger", self.pre_spin)
        g.addRow("disarm after", self.armed_timeout_spin)
        g.addRow("sample rate", self.rate_combo)
        g.addRow(self.fit_check)
        g.addRow("fit models", self.models_edit)
        g.addRow("fit window", self.fit_window_spin)
        g.addRow("run folder", self.out_edit)
        lay.addWidget(man)

        self.prediction = QLabel("Predicted surge: —")
        self.prediction.setWordWrap(True)
        self.prediction.setTextFormat(Qt.RichText)
        self.prediction.setMargin(4)
        # (the Run page shows it under the control bar, outside the form's scroll area: RunPage.interlock)

        lay.addStretch(1)
        for w in (self.beta_spin, self.gamma_spin, self.end_spin, self.margin_spin, self.duration_spin,
                  self.pre_spin, self.fit_window_spin, self.armed_timeout_spin):
            w.valueChanged.connect(self.changed)
        self.fit_check.toggled.connect(self.changed)

    FIRED_TIP = ("the valve is fired by a digital line: its actuator makes its own stroke, measured on the position "
                 "channel (the interlock predicts from the last measured stroke, or the rig's nominal one)")

    def set_fired_valve(self, fired: bool) -> None:
        """A fired valve's stroke is its own: the manoeuvre fields show the rig's default and take no input."""
        self.fired_valve = bool(fired)
        for w in (self.beta_spin, self.gamma_spin, self.end_spin):
            if fired:
                w.setValue(w.minimum())  # the special value: "rig default" (beta, gamma), 0 % (end)
            w.setToolTip(self.FIRED_TIP if fired else "")
        self._manoeuvre_enabled(not self._active)

    def _manoeuvre_enabled(self, on: bool) -> None:
        for w in (self.beta_spin, self.gamma_spin, self.end_spin):
            w.setEnabled(on and not self.fired_valve)

    def settings(self) -> dict:
        """RecordSettings keyword arguments from the form (no manoeuvre for a fired valve: its stroke is its own)."""
        fired = self.fired_valve
        beta = None if fired else (self.beta_spin.value() or None)
        gamma = None if fired else (self.gamma_spin.value() or None)
        return dict(
            duration_s=self.duration_spin.value(), pretrigger_s=self.pre_spin.value(),
            sample_rate_hz=float(self.rate_combo.currentData()), beta_per_s=beta, gamma=gamma,
            end_position_pct=0.0 if fired else self.end_spin.value(), out_dir=self.out_edit.text().strip() or "runs",
            title=self.title_edit.text().strip(), operator=self.operator_edit.text().strip(),
            specimen=self.specimen_edit.text().strip(), notes=self.notes_edit.text().strip(),
            fit=self.fit_check.isChecked(), fit_window_s=self.fit_window_spin.value(),
            surge_margin=self.margin_spin.value() / 100.0, fit_models=self._models(),
            armed_timeout_s=self.armed_timeout_spin.value() or None,
        )

    def _models(self) -> tuple:
        from velab.fitting import parse_models  # (velab.fitting.sweep: 1.7 s of imports, only when a run is set up)

        try:
            return tuple(parse_models(self.models_edit.text().strip() or "0-6"))
        except VelabError:
            return tuple(range(7))

    def save(self) -> None:
        s = self.settings()
        for key in ("operator", "specimen", "duration_s", "pretrigger_s", "sample_rate_hz", "end_position_pct",
                    "out_dir", "fit_window_s"):
            self.qs.setValue(f"run/{key}", s[key])
        self.qs.setValue("run/beta_per_s", s["beta_per_s"] or 0.0)
        self.qs.setValue("run/gamma", s["gamma"] or 0.0)
        self.qs.setValue("run/fit", "true" if s["fit"] else "false")
        self.qs.setValue("run/surge_margin_pct", self.margin_spin.value())
        self.qs.setValue("run/fit_models", self.models_edit.text())
        self.qs.setValue("run/armed_timeout_s", self.armed_timeout_spin.value())

    def show_prediction(self, pred) -> None:
        """A SurgePrediction (or None)."""
        if pred is None:
            self.prediction.setText("Predicted surge: connect the bench to get the interlock's prediction.")
            self.prediction.setStyleSheet("")
            return
        ok = bool(getattr(pred, "allowed", True))
        head = getattr(pred, "peak_head_m", float("nan"))
        surge = getattr(pred, "surge_m", float("nan"))
        ppa = getattr(pred, "peak_pressure_pa", float("nan"))
        lim = getattr(pred, "limit_pa", float("nan"))
        msg = getattr(pred, "message", "")
        verdict = "<b>within limits</b>" if ok else "<b>REFUSED by the interlock</b>"
        self.prediction.setText(
            f"Predicted surge {surge:.1f} m → peak head {head:.1f} m ({ppa / 1e5:.2f} bar; "
            f"limit {lim / 1e5:.2f} bar, {getattr(pred, 'limiting', '')}): {verdict}")
        self.prediction.setToolTip(msg)
        self.prediction.setStyleSheet("background:#e4f4e0;" if ok else "background:#fde2e1; color:#6b0d0a;")

    def show_settings_error(self, text: str) -> None:
        self.prediction.setText(f"<b>Settings:</b> {text}")
        self.prediction.setStyleSheet("background:#fde2e1; color:#6b0d0a;")

    def set_phase(self, phase: str) -> None:
        """The form is read-only while a run is armed, recording or fitting (its settings went with Arm)."""
        active = phase in ACTIVE_PHASES
        self._active = active
        for w in (self.margin_spin, self.duration_spin, self.pre_spin,
                  self.armed_timeout_spin, self.rate_combo, self.out_edit, self.fit_check, self.fit_window_spin,
                  self.models_edit):
            w.setEnabled(not active)
        self._manoeuvre_enabled(not active)
