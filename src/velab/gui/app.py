"""Starting the GUI: the QApplication, the recorder factory for the bench or the simulated rig."""

from __future__ import annotations

import sys
import traceback
from pathlib import Path

from velab.errors import VelabError


def ensure_app():
    from PySide6.QtWidgets import QApplication

    app = QApplication.instance()
    if app is None:
        app = QApplication(sys.argv[:1])
        app.setOrganizationName("velab")
        app.setApplicationName("velab-gui")
    import pyqtgraph as pg

    pg.setConfigOptions(background="w", foreground="k", antialias=False)
    return app


def recorder_factory(*, config=None, simulate: bool = False, sim_config: str = "default", material=None, rig=None):
    """A callable ``factory(**record_settings) -> Recorder`` (velab.recorder), and the rig it records.

    Raises VelabError if the recorder engine is not available or the configuration is bad.
    """
    try:
        from velab import recorder as rec
    except ModuleNotFoundError as exc:
        if exc.name and exc.name.startswith("velab.recorder"):
            raise VelabError("the recorder engine (velab.recorder) is not installed; only the archive browser works")
        raise
    if simulate:
        def make(**settings):
            s = rec.RecordSettings(**_coerce(settings))
            kw = {"sim_config": sim_config}
            if material is not None:
                kw["material"] = material
            return rec.Recorder.simulated(s, **kw)
        return make, _rig(rig)
    if config is None:
        raise VelabError("give --config BENCH.toml or --simulate")
    opener = getattr(rec, "Recorder", None)
    from_config = getattr(opener, "from_config", None)
    if from_config is None:
        raise VelabError("this recorder cannot open a bench config from the GUI (no Recorder.from_config)")

    def make(**settings):
        return from_config(config, rec.RecordSettings(**_coerce(settings)), **({"rig": rig} if rig else {}))
    return make, _rig(rig)


def _coerce(settings: dict) -> dict:
    s = dict(settings)
    if "out_dir" in s:
        s["out_dir"] = Path(s["out_dir"])
    return s


def _rig(name):
    from velab.config import load_rig

    return load_rig(name or "perugia")


def run_gui(args) -> int:
    from velab.gui.main_window import MainWindow, make_settings

    app = ensure_app()
    qs = make_settings(getattr(args, "settings", None))
    factory, rig, label, startup_error = None, None, "archive only", None
    if args.simulate or args.config:
        try:
            factory, rig = recorder_factory(config=args.config, simulate=args.simulate,
                                            sim_config=args.sim_config, material=args.material, rig=args.rig)
            label = f"simulated rig '{args.sim_config}'" if args.simulate else str(args.config)
            if args.config:
                qs.setValue("last/config", str(args.config))
        except VelabError as exc:
            startup_error = str(exc)
    else:
        try:
            rig = _rig(args.rig) if args.rig else None
        except VelabError as exc:
            startup_error = str(exc)
    win = MainWindow(settings=qs, recorder_factory=factory, rig=rig, source_label=label)

    def hook(tp, exc, tb):  # an unexpected exception in a slot: show it, keep running
        traceback.print_exception(tp, exc, tb)
        try:
            win.report_exception(exc)
        except Exception:
            pass

    sys.excepthook = hook
    if startup_error:
        win.show_message(startup_error, "error")
    if args.open:
        win.tabs.setCurrentWidget(win.archive)
        win.archive.set_folder(Path(args.open).resolve().parent)
        win.archive.open(args.open)
    win.show()
    return int(app.exec() or 0)
