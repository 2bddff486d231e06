"""Screenshots of the real window for the README and docs/gui.md, from a real simulated run.

Runs ``velab gui --simulate --material A`` in-process (the simulated rig on a 4x scaled clock,
10 kHz streaming ADC, the default EL..S6 online fit on a 20 s window), presses Connect, Arm
and Trigger in the window's control bar as soon as each is enabled, grabs the Run page during
the transient and the Fit page after the final fit, each at 1366 x 768 (a lab laptop) and at
1920 x 1080:

    docs/img/gui-run.png  docs/img/gui-fit.png            1366 x 768
    docs/img/gui-run-1920.png  docs/img/gui-fit-1920.png  1920 x 1080

The images are written only if the run completed with its online fit, no warning or error was
shown (no banner) and the best model is the one expected (``--expect-best``, default S3: material
A is an S3 material); otherwise the script says why and exits 1, writing nothing. Offscreen by
default, or under Xvfb: ``QT_QPA_PLATFORM=xcb xvfb-run -s "-screen 0 1920x1080x24" python
docs/make_screenshots.py``.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
OUT = Path(__file__).resolve().parent / "img"
SIZES = {"": (1366, 768), "-1920": (1920, 1080)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--expect-best", default="S3", help="the best model the run must give (default S3; '' for any)")
    ap.add_argument("--out", type=Path, default=OUT, help=f"folder for the images (default {OUT})")
    ap.add_argument("--clock", default="scaled:4")
    ap.add_argument("--rate", type=float, default=10000.0, help="sample rate, Hz (10000)")
    args = ap.parse_args(argv)

    from velab.configpath import DEFAULT_SIM
    from velab.gui.app import ensure_app, recorder_factory
    from velab.gui.main_window import MainWindow, make_settings
    from velab.gui.eventloop import wait_until

    app = ensure_app()
    tmp = tempfile.mkdtemp(prefix="velab-shots-")
    factory, rig = recorder_factory(simulate=True, clock=args.clock, material="A")
    win = MainWindow(settings=make_settings(os.path.join(tmp, "gui.ini")), recorder_factory=factory, rig=rig,
                     source_label=f"simulated bench '{DEFAULT_SIM}', material A")
    rp, rc = win.run_panel, win.run_controls
    rp.title_edit.setText("closure 3, material A")
    rp.operator_edit.setText("M. Rossi")
    rp.specimen_edit.setText("HDPE-110-PN10 #2")
    rp.notes_edit.setText("valve butterfly DN50, 20 °C")
    rp.duration_spin.setValue(21.0)
    rp.pre_spin.setValue(2.0)
    rp.fit_window_spin.setValue(20.0)
    rp.models_edit.setText("0-6")
    rp.rate_combo.setCurrentIndex(rp.rate_combo.findData(args.rate))
    rp.out_edit.setText(os.path.join(tmp, "runs"))
    win.resize(*SIZES[""])
    win.show()
    wait_until(lambda: False, 0.5)
    shots = {}

    def grab(name: str) -> None:
        for suffix, size in SIZES.items():
            win.resize(*size)
            wait_until(lambda: False, 0.3)
            win.live.refresh(force=True)
            wait_until(lambda: False, 0.1)
            shots[f"{name}{suffix}.png"] = win.grab()
        win.resize(*SIZES[""])

    for button in ("connect", "arm", "trigger"):  # each as soon as it is enabled, as an operator does
        if not wait_until(lambda b=button: rc.buttons[b].isEnabled(), 120):
            print(f"{button} never enabled: {win.log.texts()}", file=sys.stderr)
            return 1
        rc.buttons[button].click()
    # a few seconds of the transient, on the measured trigger's axis
    wait_until(lambda: win.live.trigger_measured and win.live.buffer.n
               and win.live.buffer.column("time_s")[-1] - win.live.offset_s > 3.2, 120)
    grab("gui-run")
    if not wait_until(lambda: win.last_summary is not None, 600) or not wait_until(
            lambda: win.fit_panel.result is not None and "final fit" in win.fit_panel.title, 120):
        print(f"the run did not end with its fit: {win.log.texts()[-6:]}", file=sys.stderr)
        return 1
    win.tabs.setCurrentWidget(win.fit_panel)
    wait_until(lambda: win.fit_panel.data is not None, 120)
    wait_until(lambda: False, 1.0)
    grab("gui-fit")
    s = win.last_summary
    problems = win.log.texts("error") + win.log.texts("warning")
    print(f"run {s.status}, best {s.best_model} (a = {s.wave_speed_m_s:.1f} m/s), fit latency "
          f"{s.fit_latency_s or float('nan'):.2f} s, {len(problems)} warnings/errors")
    win.close()
    if s.status != "completed" or s.fit is None or problems:
        print("not written: the run did not complete cleanly: " + "; ".join(problems), file=sys.stderr)
        return 1
    if args.expect_best and s.best_model != args.expect_best:
        print(f"not written: the online fit chose {s.best_model}, not {args.expect_best} (material A is an S3 "
              "material: a fit that does not find it is a finding, not a screenshot)", file=sys.stderr)
        return 1
    args.out.mkdir(parents=True, exist_ok=True)
    for name, pixmap in shots.items():
        pixmap.save(str(args.out / name))
    print("wrote " + ", ".join(str(args.out / n) for n in shots))
    return 0


if __name__ == "__main__":
    sys.exit(main())
