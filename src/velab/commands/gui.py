"""``velab gui``: the operator's window (PySide6 + pyqtgraph). Qt is imported only when it runs."""

from __future__ import annotations

import argparse

from velab.errors import VelabError


def register(sub) -> None:
    p = sub.add_parser(
        "gui",
        help="the operator's window: run tests at the bench, browse and re-fit archived runs",
        description="Open the operator GUI. With --simulate or --config it records runs through the same "
        "recorder engine as `velab record`; without them it is an archive browser. Needs the [gui] extra "
        "(PySide6, pyqtgraph). See docs/gui.md.",
    )
    src = p.add_mutually_exclusive_group()
    src.add_argument("--config", metavar="BENCH", help="bench configuration: a name (benches/BENCH.toml on the "
                     "config path) or a TOML file")
    src.add_argument("--simulate", action="store_true", help="record from the built-in simulated rig")
    p.add_argument("--sim-config", default="default", help="simulated rig configuration (with --simulate)")
    p.add_argument("--material", default=None, help="pipe material of the simulated rig, e.g. A (with --simulate)")
    p.add_argument("--clock", default=None, metavar="KIND",
                   help="simulated clock: realtime (default), fast (12x) or scaled:K (with --simulate)")
    p.add_argument("--rig", default=None, help="rig configuration name or TOML (with --simulate: the rig simulated; "
                                               "default: the bench's)")
    p.add_argument("--open", metavar="RUN.h5", help="open this run in the archive browser")
    p.add_argument("--settings", metavar="FILE.ini", help=argparse.SUPPRESS)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from velab.configpath import find_config
    from velab.inputfiles import check_input_file

    if args.config:
        check_input_file(find_config("benches", args.config), "bench configuration")
    if args.open:
        check_input_file(args.open, "run file")
    try:
        import PySide6  # noqa: F401
        import pyqtgraph  # noqa: F401
    except ImportError as exc:
        raise VelabError(f"the GUI needs PySide6 and pyqtgraph (pip install 'velab[gui]'): {exc}") from None
    from velab.gui.app import run_gui

    return run_gui(args)
