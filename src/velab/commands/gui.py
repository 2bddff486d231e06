"""``velab gui``: the operator's window (PySide6 + pyqtgraph). Qt is imported only when it runs."""

from __future__ import annotations

import argparse
import os
import sys

from velab.configpath import DEFAULT_SIM
from velab.errors import UnavailableError, VelabError

# Qt platforms that need no display server (QT_QPA_PLATFORM): no window on a screen, but they start
HEADLESS_PLATFORMS = ("offscreen", "minimal", "vnc", "eglfs", "linuxfb", "vkkhrdisplay")


def display_problem(env=None, platform: str | None = None) -> str:
    """Why Qt could not open a window here ("" when it can), decided before Qt starts: on Linux and the BSDs
    Qt without an X or Wayland display aborts the interpreter (a core dump, exit 134) instead of raising."""
    env = os.environ if env is None else env
    platform = sys.platform if platform is None else platform
    if platform.startswith(("win", "darwin", "cygwin")):
        return ""
    qpa = (env.get("QT_QPA_PLATFORM") or "").split(":", 1)[0].split(";", 1)[0].strip().lower()
    if qpa in HEADLESS_PLATFORMS:
        return ""
    x, wl = bool(env.get("DISPLAY")), bool(env.get("WAYLAND_DISPLAY"))
    if qpa == "xcb" and not x:
        return "QT_QPA_PLATFORM=xcb but $DISPLAY is not set"
    if qpa.startswith("wayland") and not wl:
        return f"QT_QPA_PLATFORM={qpa} but $WAYLAND_DISPLAY is not set"
    if not qpa and not (x or wl):
        return "neither $DISPLAY nor $WAYLAND_DISPLAY is set"
    return ""


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
    p.add_argument("--sim-config", default=DEFAULT_SIM, help=f"simulated rig configuration (with --simulate; default "
                                                          f"{DEFAULT_SIM})")
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
    why = display_problem()
    if why:
        raise UnavailableError(f"no display for the window: {why} (run it in a desktop session, with ssh -X, under "
                               "xvfb-run, or with QT_QPA_PLATFORM=offscreen for no visible window)")
    try:
        import PySide6  # noqa: F401
        import pyqtgraph  # noqa: F401
    except ImportError as exc:
        raise VelabError(f"the GUI needs PySide6 and pyqtgraph (pip install 'velab[gui]'): {exc}") from None
    from velab.gui.app import run_gui

    return run_gui(args)
