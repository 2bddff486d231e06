"""The Archive tab's fit controller: the Re-fit form and the runner of its fits (one run, several in
turn, several together) through the fit service (velab.fitservice: the fit processes of
velab.fit_worker, off the GUI's process and at a lower priority).

The GUI thread only sends requests and reads outcomes: a fit's Future and its progress messages
reach it as queued signals (velab.gui.tasks.watch), the saving of a fit into its run goes to the
GUI's thread pool. Signals: ``message(text, level)``, ``refitted(best)`` when a fit has ended,
``shown(path, RefitOutcome)`` a re-fit to show, ``stored()`` fits saved (the catalogue's rows
change), ``busy_changed(bool)``.
"""

from __future__ import annotations

from pathlib import Path

from PySide6.QtCore import QSettings, Signal
from PySide6.QtWidgets import QCheckBox, QGridLayout, QGroupBox, QLabel, QLineEdit, QProgressBar, QPushButton

from velab.gui import tasks
from velab.gui.archive_io import RefitOptions, joint_request, refit_request, store_joint, store_refit
from velab.gui.messages import describe_error
from velab.gui.widgets import ComboBox, DoubleSpinBox, SpinBox


class FitController(QGroupBox):
    message = Signal(str, str)
    refitted = Signal(str)
    shown = Signal(object, object)  # path, RefitOutcome
    stored = Signal()
    busy_changed = Signal(bool)

    def __init__(self, settings: QSettings, parent=None):
        super().__init__("Re-fit", parent)
        self.settings = settings
        self.busy = False
        self.path: Path | None = None  # the run shown (Re-fit fits it)
        self._service = None
        form = QGridLayout(self)
        form.setContentsMargins(4, 2, 4, 4)
        form.setVerticalSpacing(3)
        self.models_edit = QLineEdit(settings.value("archive/models", "0-6"))
        self.models_edit.setToolTip("models by number of Kelvin-Voigt elements: 0-6, 1-4, 1,3 (0 = EL)")
        self.window_spin = DoubleSpinBox()
        self.window_spin.setRange(0.1, 3600)
        self.window_spin.setDecimals(2)
        self.window_spin.setSuffix(" s")
        self.window_spin.setValue(float(settings.value("archive/window_s", 20.0)))
        self.method_combo = ComboBox()
        from velab.fitting import METHODS

        self.method_combo.addItems(METHODS)
        self.method_combo.setCurrentText(settings.value("archive/method", "auto"))
        self.starts_spin = SpinBox()
        self.starts_spin.setRange(0, 50)
        self.starts_spin.setSpecialValueText("all")
        self.starts_spin.setToolTip("cap on the number of starts per model (all: the full search)")
        self.reduced_check = QCheckBox("also S1r..S5r")
        self.reduced_check.setToolTip("also the reduced models S1r..S5r")
        self.save_check = QCheckBox("store in the file")
        self.save_check.setToolTip("store the fit in the run file")
        self.save_check.setChecked(True)
        for r, (label, w, label2, w2) in enumerate((("models", self.models_edit, "window", self.window_spin),
                                                     ("method", self.method_combo, "starts", self.starts_spin))):
            form.addWidget(QLabel(label), r, 0)
            form.addWidget(w, r, 1)
            form.addWidget(QLabel(label2), r, 2)
            form.addWidget(w2, r, 3)
        form.addWidget(self.reduced_check, 2, 0, 1, 2)
        form.addWidget(self.save_check, 2, 2, 1, 2)
        self.refit_button = QPushButton("Re-fit")
        self.refit_button.clicked.connect(self.start_refit)
        self.progress = QProgressBar()
        self.progress.setTextVisible(True)
        self.progress.setFormat("idle")
        self.progress.setValue(0)
        form.addWidget(self.refit_button, 3, 0, 1, 2)
        form.addWidget(self.progress, 3, 2, 1, 2)
        # the service, for the widget's end (the handler runs when only the C++ side is left)
        self._services: list = []
        self.destroyed.connect(lambda *_, held=self._services: [s.close() for s in held])
        self._update()

    # ------------------------------------------------------------------ state
    def service(self):
        """The fit service of this window: one fit process (velab.fit_worker), started on the first fit."""
        if self._service is None:
            from velab.fitservice.service import FitService

            self._service = FitService.processes(1)
            self._services.append(self._service)
        return self._service

    def options(self) -> RefitOptions:
        return RefitOptions(
            models=self.models_edit.text().strip() or "0-6", window_s=self.window_spin.value(),
            method=self.method_combo.currentText(), reduced=self.reduced_check.isChecked(),
            starts=self.starts_spin.value() or None, save=self.save_check.isChecked(),
        )

    def set_run(self, path, duration_s: float | None = None) -> None:
        """The run shown: Re-fit fits it; a window longer than its record after the trigger is cut to it."""
        self.path = Path(path) if path is not None else None
        if duration_s and duration_s > 0 and self.window_spin.value() > duration_s:
            self.window_spin.setValue(round(min(20.0, duration_s), 2))
        self._update()

    def _set_busy(self, busy: bool) -> None:
        self.busy = busy
        self._update()
        self.busy_changed.emit(busy)

    def _update(self) -> None:
        self.refit_button.setEnabled(self.path is not None and not self.busy)

    def _submit(self, request, on_done, on_error, on_progress=None):
        sink = tasks.progress_sink(on_progress, owner=self).sink if on_progress is not None else None
        fut = self.service().submit(request, progress=sink)
        tasks.watch(fut, on_done=on_done, on_error=on_error, owner=self)
        return fut

    # ------------------------------------------------------------------ one run
    def start_refit(self) -> None:
        if self.path is None or self.busy:
            return
        opts = self.options()
        self.settings.setValue("archive/models", opts.models)
        self.settings.setValue("archive/window_s", opts.window_s)
        self.settings.setValue("archive/method", opts.method)
        path = self.path
        try:
            request = refit_request(path, opts)
        except Exception as exc:  # noqa: BLE001 - bad options: one message
            self._failed(exc)
            return
        self._set_busy(True)
        self.progress.setRange(0, 0)
        self.progress.setFormat("starting…")
        self.message.emit(f"Re-fitting {path.name}: models {opts.models}, window {opts.window_s:g} s, "
                          f"method {opts.method}", "info")
        self._submit(request, lambda r: self._store(path, r, opts), self._failed, self._progress)

    def _progress(self, done: int, total: int, name: str) -> None:
        self.progress.setRange(0, total)
        self.progress.setValue(done)
        self.progress.setFormat(f"{done}/{total}: fitted {name}")

    def _store(self, path, result, opts) -> None:
        tasks.submit(store_refit, path, result, opts, owner=self, on_done=lambda out: self._refit_done(out, path),
                     on_error=self._failed)

    def _failed(self, exc) -> None:
        self.progress.setRange(0, 1)
        self.progress.setValue(0)
        self.progress.setFormat("failed")
        self._set_busy(False)
        level, text = describe_error(exc)
        self.message.emit(f"Re-fit failed: {text}", level)

    def _refit_done(self, out, path) -> None:
        self.progress.setRange(0, 1)
        self.progress.setValue(1)
        r = out.result
        self.progress.setFormat(f"done in {r.duration_s:.1f} s: best {r.best.name}")
        self._set_busy(False)
        self.shown.emit(path, out)
        text = f"Re-fit of {path.name}: best {r.best.name} (a = {r.best.wave_speed_m_s:.1f} m/s) in {r.duration_s:.1f} s"
        text += f", saved as /entry/fits/{out.saved_as}" if out.saved_as else ""
        self.message.emit(text, "info")
        if out.note:
            self.message.emit(out.note, "warning")
        if out.saved_as:
            self.stored.emit()  # the run's row shows its new fit
        self.refitted.emit(r.best.name)

    # ------------------------------------------------------------------ several runs, in turn
    def refit_many(self, paths: list[str]) -> None:
        """Re-fit each run in turn with the form's settings; one message per run, failures included."""
        if not paths or self.busy:
            return
        opts = self.options()
        try:
            requests = [refit_request(p, opts) for p in paths]
        except Exception as exc:  # noqa: BLE001
            self._failed(exc)
            return
        self._set_busy(True)
        self.progress.setRange(0, len(paths))
        self.progress.setValue(0)
        self.message.emit(f"Re-fitting {len(paths)} runs: models {opts.models}, window {opts.window_s:g} s", "info")
        outcomes: dict[str, str] = {}

        def one_done(p: str, line: str) -> None:
            outcomes[p] = line
            n = len(outcomes)
            self.progress.setRange(0, len(paths))
            self.progress.setValue(n)
            self.progress.setFormat(f"{n}/{len(paths)}: re-fitted {Path(p).name}")
            if n == len(paths):
                self._refit_many_done([(p, outcomes[p]) for p in paths])

        def failed(p, exc):
            one_done(p, f"failed: {describe_error(exc)[1]}")

        def stored(p, out):
            best = out.result.best
            line = f"best {best.name} (a = {best.wave_speed_m_s:.1f} m/s)" + (
                f", saved as {out.saved_as}" if out.saved_as else "")
            one_done(p, line + (f"; {out.note}" if out.note else ""))

        for p, req in zip(paths, requests):
            self._submit(req, lambda r, p=p: tasks.submit(store_refit, p, r, opts, owner=self,
                                                          on_done=lambda out, p=p: stored(p, out),
                                                          on_error=lambda exc, p=p: failed(p, exc)),
                         lambda exc, p=p: failed(p, exc))

    def _refit_many_done(self, outcomes) -> None:
        self._set_busy(False)
        failed = sum(1 for _, line in outcomes if line.startswith("failed"))
        for p, line in outcomes:
            self.message.emit(f"Re-fit of {Path(p).name}: {line}", "warning" if line.startswith("failed") else "info")
        self.progress.setFormat(f"{len(outcomes) - failed} of {len(outcomes)} re-fitted")
        self.refitted.emit(f"{len(outcomes) - failed}/{len(outcomes)}")
        self.stored.emit()  # the saved fits change the rows

    # ------------------------------------------------------------------ several runs, together
    def fit_together(self, paths: list[str]) -> None:
        """The joint fit of the runs (one wall for all) with the form's models, window and search, saved into each."""
        if len(paths) < 2 or self.busy:
            return
        opts = self.options()
        try:
            request = joint_request(paths, opts)
        except Exception as exc:  # noqa: BLE001
            self._failed(exc)
            return
        self._set_busy(True)
        self.progress.setRange(0, 0)
        self.progress.setFormat(f"fitting {len(paths)} runs together…")
        self.message.emit(f"Fitting {len(paths)} runs together: models {opts.models}, window {opts.window_s:g} s",
                          "info")

        def fitted(result):
            tasks.submit(store_joint, paths, result, opts, owner=self,
                         on_done=lambda name: self._joint_done(result, name, len(paths)), on_error=self._failed)
        self._submit(request, fitted, self._failed, self._progress)

    def _joint_done(self, result, name, n: int) -> None:
        self.progress.setRange(0, 1)
        self.progress.setValue(1)
        best = result.best
        self.progress.setFormat(f"joint fit: best {best.name}")
        self._set_busy(False)
        text = f"Joint fit of {n} runs: best {best.name} (a = {best.wave_speed_m_s:.1f} m/s)"
        text += f", saved as /entry/fits/{name} in each run" if name else " (not saved)"
        self.message.emit(text, "info")
        for note in result.notes or []:
            self.message.emit(f"Joint fit: {note}", "info")
        self.refitted.emit(best.name)
        if name:
            self.stored.emit()  # the runs' rows show the joint fit as their latest
