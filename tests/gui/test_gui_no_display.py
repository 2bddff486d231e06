"""``velab gui`` where no window can open: one line and exit 5 (FAILURE: the display the command needs is
unavailable), decided before Qt starts (Qt without a display aborts the interpreter: exit 134, a core)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from velab.commands.gui import display_problem


@pytest.mark.parametrize("env, why", [
    ({}, "neither $DISPLAY nor $WAYLAND_DISPLAY is set"),
    ({"QT_QPA_PLATFORM": "xcb"}, "QT_QPA_PLATFORM=xcb but $DISPLAY is not set"),
    ({"QT_QPA_PLATFORM": "wayland", "DISPLAY": ":0"}, "QT_QPA_PLATFORM=wayland but $WAYLAND_DISPLAY is not set"),
    ({"DISPLAY": ":0"}, ""), ({"WAYLAND_DISPLAY": "wayland-0"}, ""),
    ({"QT_QPA_PLATFORM": "offscreen"}, ""), ({"QT_QPA_PLATFORM": "minimal"}, ""),
    ({"QT_QPA_PLATFORM": "xcb", "DISPLAY": ":99"}, ""),
])
def test_display_problem(env, why):
    assert display_problem(env, "linux") == why


def test_no_display_check_on_windows_and_macos():
    assert display_problem({}, "win32") == "" and display_problem({}, "darwin") == ""


@pytest.mark.parametrize("args", [["gui"], ["gui", "--simulate"]])
def test_velab_gui_without_a_display_is_one_line_and_exit_5(args):
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "QT_QPA_PLATFORM")}
    p = subprocess.run([sys.executable, "-m", "velab.cli", *args], capture_output=True, text=True, env=env,
                       timeout=120)
    assert p.returncode == 5, (p.returncode, p.stderr)
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("velab: no display for the window:"), p.stderr
    assert "xvfb-run" in lines[0] and "QT_QPA_PLATFORM=offscreen" in lines[0]
