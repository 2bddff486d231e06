"""The operator window on a real X server (Xvfb) at 1366 x 768 and 1920 x 1080 (issue 50): screenshots of
every phase of a run and of the Archive tab with 1,000 catalogued runs, and what they show: every control
inside the window and the screen, not cut by a scroll area, its text whole; the interlock's line; ten
archive rows with their whole start time; the device table's steady head before arming, in the rig's
units; a disabled Abort drawn as disabled; the fitting phase; the fit's summary in the panel; a bad model
in the filter marked. tests/gui/xvfb_shots.py takes the shots (one process per screen size); with
VELAB_SCREENSHOTS=DIR the PNGs (and what each shows, as JSON) are kept in DIR: look at them, they are what
an operator sees."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pyqtgraph")

HERE = Path(__file__).resolve().parent
XVFB = shutil.which("xvfb-run")
pytestmark = [pytest.mark.gui, pytest.mark.skipif(
    XVFB is None, reason="xvfb-run not found (Debian/Ubuntu package xvfb): the real-screen tests need an X server")]
CHECKS = ("visible", "unclipped", "in_window", "on_screen", "text_fits")
RUN_PHASES = {"connected": "ready", "armed": "armed", "recording": "recording", "fitting": "fitting",
              "ended": "completed", "refused": "completed"}


def _shoot(out: Path, size, *args, timeout=300) -> Path:
    env = dict(os.environ, XDG_CACHE_HOME=str(out / "cache"))
    cmd = [XVFB, "-a", "-s", f"-screen 0 {size[0]}x{size[1]}x24", sys.executable, str(HERE / "xvfb_shots.py"),
           *args, "--out", str(out)]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
    keep = os.environ.get("VELAB_SCREENSHOTS")  # a folder to keep the shots in, to look at them
    if keep:
        dest = Path(keep) / f"{size[0]}x{size[1]}-{'-'.join(args)}"
        shutil.copytree(out, dest, dirs_exist_ok=True, ignore=shutil.ignore_patterns("cache"))
    assert p.returncode == 0, f"xvfb_shots {' '.join(args)} failed (exit {p.returncode}): {p.stderr[-2000:]}"
    return out


@pytest.fixture(scope="module")
def laptop_run(tmp_path_factory):
    """Every phase of a real simulated run at 1366 x 768."""
    return _shoot(tmp_path_factory.mktemp("shots-1366"), (1366, 768), "run")


@pytest.fixture(scope="module")
def laptop_archive(tmp_path_factory):
    return _shoot(tmp_path_factory.mktemp("archive-1366"), (1366, 768), "archive")


def _shot(folder: Path, name: str) -> dict:
    doc = json.loads((folder / f"{name}.json").read_text())
    doc["png"] = folder / f"{name}.png"
    return doc


def _assert_whole(doc: dict, skip=()) -> None:
    """The shot is the screen, the window fills it, and every essential widget can be seen whole."""
    from PIL import Image

    img = Image.open(doc["png"])
    assert list(img.size) == doc["screen"], "the screenshot is not the X screen"
    assert doc["window"] == [0, 0, *doc["screen"]], f"the window does not fill the screen: {doc['window']}"
    assert len(img.convert("RGB").getcolors(1 << 20) or []) > 50, "a blank screenshot"
    bad = {w["name"]: [k for k in CHECKS if not w[k]] for w in doc["widgets"] if w["name"] not in skip}
    bad = {k: v for k, v in bad.items() if v}
    assert not bad, f"{doc['name']}: widgets cut or off screen: {bad}"


def _mean_rgb(doc: dict, name: str):
    from PIL import Image, ImageStat

    x, y, w, h = next(w["rect"] for w in doc["widgets"] if w["name"] == name)
    crop = Image.open(doc["png"]).convert("RGB").crop((x + 3, y + 3, x + w - 3, y + h - 3))
    return ImageStat.Stat(crop).mean


@pytest.mark.parametrize("phase", list(RUN_PHASES))
def test_every_phase_shows_every_control_whole(laptop_run, phase):
    doc = _shot(laptop_run, phase)
    _assert_whole(doc)
    assert doc["phase"] == RUN_PHASES[phase], (phase, doc["phase"], doc["detail"])
    interlock = next(w for w in doc["widgets"] if w["name"] == "interlock")
    # (the buttons as they were when the phase was seen: doc["phase"] and these are one moment)
    enabled = {k.split(":")[1] for k, on in doc["controls_at_phase"].items() if on}
    if phase == "refused":
        assert "REFUSED by the interlock" in interlock["text"]
        assert "arm" not in enabled, "Arm (Reopen + Arm) offered while the interlock refuses"
    else:
        assert "within limits" in interlock["text"]
    if phase == "fitting":  # the final fit runs while the rest of the run records
        assert "final fit" in doc["detail"] and enabled <= {"stop", "abort"}


def test_the_device_table_shows_the_steady_head_before_arming(laptop_run):
    doc = _shot(laptop_run, "connected")
    rows = {r[0]: r for r in doc["devices"]["texts"]}
    assert doc["engine_phase"] == "ready"
    head = rows["head at the valve"]
    assert head[2] == "m" and abs(float(head[1]) - 34.72) < 0.5, head  # the rig's steady head
    assert rows["flow"][2] == "l/s" and re.fullmatch(r"\d\.\d{3}", rows["flow"][1]), rows["flow"]
    assert rows["valve position"][1:3] == ["100.0", "%"]
    ended = _shot(laptop_run, "ended")
    for r in doc["devices"]["texts"] + ended["devices"]["texts"]:
        assert "e-" not in r[1] and "m3/s" not in r[2], r  # no 7.605e-08 %, no m3/s beside l/s


def test_controls_look_as_enabled_as_they_are(laptop_run):
    r, g, b = _mean_rgb(_shot(laptop_run, "connected"), "button:abort")  # Abort disabled: grey, as the others
    assert abs(r - g) < 20 and abs(r - b) < 20, f"a disabled Abort drawn coloured: {r:.0f}, {g:.0f}, {b:.0f}"
    r, g, b = _mean_rgb(_shot(laptop_run, "recording"), "button:abort")  # live: red
    assert r > g + 60 and r > b + 60, f"a live Abort not red: {r:.0f}, {g:.0f}, {b:.0f}"


def test_the_fit_panel_shows_the_result_summary(laptop_run):
    doc = _shot(laptop_run, "fitted")
    _assert_whole(doc)
    text = doc["summary_text"]
    assert doc["status"] == "completed"
    assert re.search(r"Best model (EL|S\d)", text) and "a = " in text and "±" in text, text
    assert "noise ratio" in text and ("KV" in text or "elastic wall" in text), text


def test_the_archive_shows_ten_whole_rows_of_a_thousand_and_every_control(laptop_archive):
    doc = _shot(laptop_archive, "archive")
    _assert_whole(doc)
    table = doc["table"]
    assert table["rows"] == 1000 and table["rows_visible"] >= 10, table["rows_visible"]
    assert not table["cut_cells"], f"cells cut: {table['cut_cells']}"
    starts = [row[0] for row in table["texts"]]
    assert all(re.fullmatch(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d", s) for s in starts), starts
    assert len(set(starts)) == len(starts), "same-day runs look alike"


def test_a_bad_model_in_the_filter_is_marked(laptop_archive):
    doc = _shot(laptop_archive, "archive-bad-filter")
    _assert_whole(doc)
    assert "no such model" in doc["best_filter_tip"] and "background" in doc["best_filter_style"]
    label = next(w for w in doc["widgets"] if w["name"] == "index label")
    assert "'S9' ignored" in label["text"] and doc["table"]["rows"] == 1000  # ignored, not "no row"


@pytest.mark.parametrize("what", ["run", "archive"])
def test_full_hd_shows_every_control_whole(tmp_path, what):
    out = _shoot(tmp_path, (1920, 1080), *(("run", "--quick") if what == "run" else ("archive",)))
    for name in (("connected", "refused") if what == "run" else ("archive",)):
        _assert_whole(_shot(out, name))
    if what == "archive":
        assert _shot(out, "archive")["table"]["rows_visible"] >= 10
