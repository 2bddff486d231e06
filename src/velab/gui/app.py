"""Starting the GUI: the QApplication, the recorder factory for the bench or the simulated rig."""

from __future__ import annotations

import sys
import traceback
from pathlib import Path

import pyqtgraph as pg
from PySide6.QtWidgets import QApplication

from velab import recording as rec
from velab.config import load_rig
from velab.configpath import DEFAULT_SIM
from velab.drivers.base import DeviceError
from velab.drivers.bench import load_bench
from velab.errors import VelabError
from velab.gui.main_window import MainWindow, make_settings
from velab.recording.settings import RecordSettings


def ensure_app():
    app = QApplication.instance()
    if app is None:
        app = QApplication(sys.argv[:1])
        app.setOrganizationName("velab")
        app.setApplicationName("velab-gui")
    pg.setConfigOptions(background="w", foreground="k", antialias=False, exitCleanup=False)
    return app


def preload(simulate: bool) -> None:
    """Import (and load the compiled kernels of: the filters, the simulated rig's MOC) what a run will need, now,
    before the window shows: an import or a kernel load on an engine thread holds the GIL for tens
    of milliseconds at a time (extension modules, numba's cache), which the GUI thread would wait
    through during the operator's first run (docs/gui.md, "Latency")."""
    import velab.fitting  # noqa: F401
    import velab.model  # noqa: F401 - the fit panel's model curves
    from velab import filters

    filters.warm_up()  # the fit panel's model curves filter the coupling's head (velab.fitting.flows)

    if simulate:
        import velab.simulators.bench  # noqa: F401
        from velab.moc import warm_up

        warm_up()


def recorder_factory(*, config=None, simulate: bool = False, sim_config: str = DEFAULT_SIM, material=None, rig=None,
                     clock: str = "realtime"):
    """``(factory, rig)``: ``factory(**record_settings) -> velab.recording.Recorder`` and the rig it records;
    ``factory.make_settings(**record_settings) -> RecordSettings`` for the next arm on the same Recorder.

    The factory runs on the controller's worker thread (it starts the simulated rig or
    loads the bench); it creates the run folder if needed. Raises VelabError for a bad
    configuration or a missing recorder engine.
    """
    preload(simulate)
    if simulate:
        from velab.simulators.bench import load_sim_config

        _, doc = load_sim_config(sim_config)
        the_rig = load_rig(rig or doc.get("rig", "perugia"))

        def make(**settings):
            s = rec.RecordSettings(**_coerce(settings))
            # a rig named with --simulate is the rig simulated (as velab record --simulate --rig)
            return rec.Recorder.simulated(s, sim_config=sim_config, material=material, clock=clock, rig=rig)
        make.make_settings = _record_settings
        return make, the_rig
    if config is None:
        raise VelabError("give --config BENCH.toml or --simulate")
    try:
        bench = load_bench(config)
    except DeviceError as exc:
        raise VelabError(str(exc)) from None
    the_rig = load_rig(rig or "perugia")

    def make(**settings):
        return rec.Recorder(bench, the_rig, rec.RecordSettings(**_coerce(settings)))
    make.make_settings = _record_settings
    return make, the_rig


def _record_settings(**settings):
    """The form's values as RecordSettings for a connected Recorder's next arm (creates the run folder)."""
    return RecordSettings(**_coerce(settings))


def _coerce(settings: dict) -> dict:
    s = dict(settings)
    if "out_dir" in s:
        s["out_dir"] = Path(s["out_dir"]).expanduser()
        s["out_dir"].mkdir(parents=True, exist_ok=True)
    return s


def _rig(name):
    return load_rig(name or "perugia")


def run_gui(args) -> int:
    app = ensure_app()
    qs = make_settings(getattr(args, "settings", None))
    factory, rig, label, startup_error = None, None, "archive only", None
    if args.simulate or args.config:
        try:
            factory, rig = recorder_factory(config=args.config, simulate=args.simulate,
                                            sim_config=args.sim_config, material=args.material, rig=args.rig,
                                            clock=getattr(args, "clock", None) or "realtime")
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
