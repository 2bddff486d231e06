"""Screenshots of the real window for the README: docs/img/gui-run.png and docs/img/gui-fit.png.

Runs ``velab gui --simulate`` in-process (simulated rig, 10 kHz, fast clock), arms and
triggers a run through the window, grabs the Run page during the transient and the Fit
page after the final fit. Works offscreen (default) or under Xvfb
(``QT_QPA_PLATFORM=xcb xvfb-run python docs/make_screenshots.py``).
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
OUT = Path(__file__).resolve().parent / "img"


def main() -> int:
    from velab.gui.app import ensure_app, recorder_factory
    from velab.gui.main_window import MainWindow, make_settings

    app = ensure_app()
    tmp = tempfile.mkdtemp(prefix="velab-shots-")
    factory, rig = recorder_factory(simulate=True, clock="scaled:4", material="A")
    win = MainWindow(settings=make_settings(os.path.join(tmp, "gui.ini")), recorder_factory=factory, rig=rig,
                     source_label="simulated rig 'default'")
    rp = win.run_panel
    rp.title_edit.setText("closure 3, material A")
    rp.operator_edit.setText("M. Rossi")
    rp.specimen_edit.setText("HDPE-110-PN10 #2")
    rp.notes_edit.setText("valve butterfly DN50, 20 °C")
    rp.duration_spin.setValue(21.0)
    rp.pre_spin.setValue(2.0)
    rp.fit_window_spin.setValue(20.0)
    rp.rate_combo.setCurrentIndex(rp.rate_combo.findData(10000.0))
    rp.out_edit.setText(os.path.join(tmp, "runs"))
    win.resize(1366, 768)
    win.show()

    def spin(seconds, until=None):
        t_end = time.perf_counter() + seconds
        while time.perf_counter() < t_end and not (until and until()):
            app.processEvents()
            time.sleep(0.002)

    spin(0.5)
    win.arm()
    spin(60, lambda: win.controller.phase == "pretrigger")
    spin(30, lambda: win.live.samples_received >= 2.0 * 10000)
    win.controller.trigger()
    spin(30, lambda: win.controller.phase == "transient")
    spin(1.6)  # a few seconds of the transient (scaled clock)
    win.live.refresh(force=True)
    app.processEvents()
    OUT.mkdir(parents=True, exist_ok=True)
    win.grab().save(str(OUT / "gui-run.png"))
    spin(240, lambda: win.last_summary is not None)
    spin(60, lambda: win.fit_panel.data is not None)
    win.tabs.setCurrentWidget(win.fit_panel)
    spin(0.5)
    win.grab().save(str(OUT / "gui-fit.png"))
    print(f"wrote {OUT / 'gui-run.png'} and {OUT / 'gui-fit.png'} "
          f"(run {win.last_summary.status}, best {win.last_summary.best_model})")
    win.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
