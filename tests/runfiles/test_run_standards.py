"""Run files that standard tools read (issue 12 item 5) and that describe themselves (issue 11 item 5).

h5dump, nexusformat's nxcheck, xarray/h5netcdf and h5py-SWMR read real files; units
are UDUNITS; strings UTF-8; the doc's tree is the files' tree; the manoeuvre is the
commanded one everywhere; file_name, slow-channel times and recovered end_time are right.
"""

from __future__ import annotations

import datetime as dt
import json
import re
import shutil
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import h5py
import numpy as np
import pytest

from velab.cli import main
from velab.config import load_rig
from velab.runfiles import Channel, RunWriter, read_run, recover_run
from velab.runfiles import layout as L
from velab.runfiles.listing import BEGIN, END, blocks, sample_files

DOC = Path(__file__).resolve().parents[2] / "docs" / "run-format.md"


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A synthetic run with a fit, and a simulated recording with its online fit (as the doc shows them)."""
    return sample_files(tmp_path_factory.mktemp("standard"))


def test_doc_tree_is_the_files_tree(files):
    text = DOC.read_text()
    for key, body in blocks(files).items():
        m = re.search(re.escape(BEGIN.format(key)) + r"\n```\n(.*?)\n?```\n" + re.escape(END.format(key)), text, re.S)
        assert m, f"{DOC}: no generated layout block for {key}"
        assert m.group(1).rstrip("\n") == body, (
            f"docs/run-format.md and a real {key} run differ: run "
            "`python -m velab.runfiles.listing --update docs/run-format.md` and review the diff")


@pytest.mark.skipif(shutil.which("h5dump") is None, reason="h5dump (Debian hdf5-tools) not installed")
@pytest.mark.parametrize("kind", ["synth", "recorded"])
def test_h5dump_reads_a_finished_run(files, kind):
    out = subprocess.run(["h5dump", str(files[kind])], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert 'DATASET "head"' in out.stdout and 'GROUP "fits"' in out.stdout and "h5dump error" not in out.stderr


@pytest.mark.parametrize("kind", ["synth", "recorded"])
def test_nexusformat_check_reports_no_error(files, kind):
    import nexusformat  # noqa: F401 - a declared test dependency: missing is a failure, not a skip
    out = subprocess.run([sys.executable, "-m", "nexusformat.scripts.nxcheck", "-e", str(files[kind])],
                         capture_output=True, text=True, timeout=120)
    text = re.sub(r"\x1b\[[0-9;]*m", "", out.stdout + out.stderr)
    assert "Total number of errors: 0" in text, text


@pytest.mark.parametrize("kind", ["synth", "recorded"])
def test_xarray_sees_named_axes(files, kind):
    import h5netcdf  # noqa: F401 - declared test dependencies
    import xarray as xr
    run = read_run(files[kind])
    with xr.open_dataset(files[kind], engine="h5netcdf", group="entry/data") as ds:
        assert dict(ds.sizes) == {"time": run.n_samples}  # no phony_dim_N
        assert ds["head"].dims == ("time",) and "time" in ds.coords
        np.testing.assert_array_equal(ds["time"].values, run.time_s)
        for name in run.channels:
            assert ds[name].dims == ("time",)
        assert ds["head"].attrs["units"] == "m"


def _all_units(path) -> set[str]:
    found = set()

    def visit(_, obj):
        if "units" in obj.attrs:
            found.add(L.to_str(obj.attrs["units"]))

    with h5py.File(path, "r") as fh:
        fh.visititems(visit)
    return found


def test_units_are_udunits(files):
    used = _all_units(files["synth"]) | _all_units(files["recorded"])
    assert used <= L.UDUNITS, used - L.UDUNITS
    assert {"m", "s", "Pa", "Pa.s", "Pa-1", "s-1", "m3/s", "1", "%"} <= used
    if shutil.which("udunits2"):  # every spelling velab writes parses (Debian udunits-bin)
        for u in sorted(L.UDUNITS):
            out = subprocess.run(["udunits2", "-H", u, "-W", ""], capture_output=True, text=True, timeout=10)
            assert "Don't recognize" not in out.stdout + out.stderr, u


def test_numeric_datasets_carry_units(files):
    missing = []

    def visit(name, obj):
        if isinstance(obj, h5py.Dataset) and obj.dtype.kind in "fiu" and "units" not in obj.attrs \
                and "/fits/" not in f"/{name}/":
            missing.append(name)

    for p in files.values():
        with h5py.File(p, "r") as fh:
            fh.visititems(visit)
    assert missing == []


def test_strings_are_utf8(files):
    bad = []

    def visit(name, obj):
        if isinstance(obj, h5py.Dataset):
            s = h5py.check_string_dtype(obj.dtype)
            if s is not None and s.encoding != "utf-8":
                bad.append(name)

    for p in files.values():
        with h5py.File(p, "r") as fh:
            fh.visititems(visit)
            assert h5py.check_string_dtype(fh["entry/title"].dtype).length is None  # variable length
    assert bad == []


def test_file_name_is_the_final_name(files, tmp_path):
    csv = tmp_path / "rec.csv"
    csv.write_text("time,head\n" + "".join(f"{i * 0.001 - 0.005},30\n" for i in range(20)))
    out = tmp_path / "imported.h5"
    assert main(["import", str(csv), "--rig", "perugia", "-o", str(out)]) == 0
    for p in (files["synth"], files["recorded"], out):
        assert read_run(p).file_name == Path(p).name


def test_events_are_not_cut_and_status_is_rewritten_under_swmr(tmp_path):
    long = "valve fault: " + "é" * 1500  # 3 kB of UTF-8: three fixed-size rows in a SWMR file
    for swmr in (True, False):
        p = tmp_path / f"w{swmr}.h5"
        w = RunWriter(p, load_rig("perugia"), sample_rate_hz=100.0, swmr=swmr)
        w.append(np.arange(20) / 100.0, head=np.full(20, 30.0))
        w.event(0.1, "fault", long)
        w.event(0.2, "note", "short")
        w.set_status("recording", "é" * 300)
        w.flush()
        with h5py.File(p, "r", swmr=swmr) as live:  # a reader sees the rewritten status while recording
            assert L.to_str(live["entry/status_reason"][()]) == "é" * 300
        w.close("stopped", "by the operator ✓")
        r = read_run(p)
        assert r.events == [(0.1, "fault", long), (0.2, "note", "short")]
        assert r.status == "stopped" and r.status_reason == "by the operator ✓"


def test_dimension_scale_is_attached_to_every_fast_channel(files):
    with h5py.File(files["recorded"], "r") as fh:
        data = fh["entry/data"]
        assert data["time"].is_scale
        for name, ds in data.items():
            if name != "time":
                assert ds.dims[0][0] == data["time"], name


def test_slow_channel_times_are_the_right_instants(tmp_path):
    """NXlog time@start + time is the instant of the reading (it used to be 2-4 s off)."""
    p = tmp_path / "slow.h5"
    w = RunWriter(p, load_rig("perugia"), sample_rate_hz=100.0, slow_channels=(Channel("flow", "m3/s"),))
    start = dt.datetime.fromisoformat(L.read_str(w._fh["entry"], "start_time")).timestamp()
    readings = np.array([start + 2.5, start + 3.0])
    w.append_slow("flow", [-0.5, 0.0], [3.6e-3, 3.5e-3], epoch_s=readings)
    before = dt.datetime.now().timestamp()
    w.append_slow("flow", 0.5, 3.4e-3)  # no host time given: now
    w.close()
    with h5py.File(p, "r") as fh:
        g = fh["entry/instrument/flow"]
        t0 = dt.datetime.fromisoformat(L.to_str(g["time"].attrs["start"])).timestamp()
        instants = t0 + g["time"][()]
        np.testing.assert_allclose(instants[:2], readings, atol=2e-3)  # ms: the ISO string's resolution
        assert before - 2e-3 <= instants[2] <= dt.datetime.now().timestamp() + 2e-3
        np.testing.assert_array_equal(g["axis_time"][()], [-0.5, 0.0, 0.5])


def test_recorded_slow_times_agree_with_the_host_clock_of_the_samples(files):
    """In a real recording, a slow reading's instant (start + time) matches the host clock of the fast
    sample at its axis time, within the acquisition's block latency: up to 0.55 s of host time under two
    suites at once. A reading put on the wrong clock is off by seconds (the fast clock's axis runs 12 x the
    host's: 1.8 s of axis between two polls)."""
    with h5py.File(files["recorded"], "r") as fh:
        g = fh["entry/instrument/flow"]
        t0 = dt.datetime.fromisoformat(L.to_str(g["time"].attrs["start"])).timestamp()
        instants, axis = t0 + g["time"][()], g["axis_time"][()]
        t, host = fh["entry/data/time"][()], fh["entry/data/host_time"][()]
    inside = (axis >= t[0]) & (axis <= t[-1])
    assert inside.sum() >= 2
    expected = np.interp(axis[inside], t, host)
    assert np.abs(instants[inside] - expected).max() < 1.0


KILLED = textwrap.dedent(
    """
    import os, signal, sys, numpy as np
    from velab.config import load_rig
    from velab.runfiles import RunWriter
    w = RunWriter(sys.argv[1], load_rig("perugia"), sample_rate_hz=100.0)
    w.append(np.arange(500) / 100.0, head=np.full(500, 30.0))
    w.flush()
    os.kill(os.getpid(), signal.SIGKILL)
    """
)


def test_recovered_run_has_its_end_time(tmp_path):
    p = tmp_path / "killed.h5"
    assert subprocess.run([sys.executable, "-c", KILLED, str(p)], timeout=60).returncode == -signal.SIGKILL
    assert read_run(p).end_time == ""
    copy, n = recover_run(p)
    r = read_run(copy)
    assert n == 500 and r.end_time and r.incomplete
    end = dt.datetime.fromisoformat(r.end_time).timestamp()
    assert abs(end - p.stat().st_mtime) < 1.0  # the writer's last write


LIVE_WRITER = textwrap.dedent(
    """
    import sys, time, numpy as np
    from velab.config import load_rig
    from velab.runfiles import RunWriter
    w = RunWriter(sys.argv[1], load_rig("perugia"), sample_rate_hz=1000.0, title="live")
    i = 0
    while True:
        t = (np.arange(100) + i) / 1000.0
        w.append(t, head=30 + t)
        w.event(float(t[0]), "block", f"block {i}")
        i += 100
        w.flush()
        print(i, flush=True)
        time.sleep(0.005)
    """
)


def test_h5py_swmr_reader_follows_a_recording(tmp_path):
    path = tmp_path / "live.h5"
    proc = subprocess.Popen([sys.executable, "-c", LIVE_WRITER, str(path)], stdout=subprocess.PIPE, text=True)
    try:
        while int(proc.stdout.readline()) < 1000:
            pass
        with h5py.File(path, "r", swmr=True) as f:  # plain h5py, no velab
            head, time_ = f["entry/data/head"], f["entry/data/time"]
            n0 = time_.shape[0]
            while int(proc.stdout.readline()) < n0 + 1000:
                pass
            time_.refresh()
            head.refresh()
            n1 = time_.shape[0]
            assert n1 > n0 >= 1000
            t = time_[:n1]
            np.testing.assert_allclose(head[:n1], 30 + t)
            assert L.to_str(f["entry/status"][()]) == "recording"
            f["entry/events/message"].refresh()
            assert f["entry/events/message"].shape[0] >= 10
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)


def test_non_default_manoeuvre_is_the_runs_everywhere(tmp_path):
    """One source of truth: a run written with beta 10 says 10 in /entry/manoeuvre and in the rig
    snapshot, and reads back with it (velab fit used the rig's default 32)."""
    p = tmp_path / "m.h5"
    rig = load_rig("perugia")
    assert rig.manoeuvre.beta_per_s != 10.0
    w = RunWriter(p, rig, sample_rate_hz=100.0, manoeuvre={"beta": (10.0, "1/s"), "gamma": (-4.0, ""),
                                                          "end_position": (5.0, "%")},
                  bench={"name": "bench", "devices": {"adc": {"profile": {"channels": 8}}}},
                  device_profiles={"adc": {"channels": 8, "rate_hz": 10000}}, devices={"adc": {"serial": "A1"}})
    w.append(np.arange(20) / 100.0, head=np.full(20, 30.0))
    w.close()
    r = read_run(p)
    assert (r.rig.manoeuvre.beta_per_s, r.rig.manoeuvre.gamma) == (10.0, -4.0)
    assert r.manoeuvre["end_position"] == 5.0
    with h5py.File(p, "r") as fh:
        snap = json.loads(fh["entry/sample/rig_json"][()])["manoeuvre"]
        assert (snap["beta_per_s"], snap["gamma"]) == (10.0, -4.0)
        assert fh["entry/manoeuvre/beta"][()] == 10.0 and fh["entry/manoeuvre/beta"].attrs["units"] == "s-1"
        assert json.loads(fh["entry/instrument/device_profiles_json"][()])["adc"]["rate_hz"] == 10000
        assert json.loads(fh["entry/instrument/devices_json"][()])["adc"]["serial"] == "A1"
        assert json.loads(fh["entry/instrument/bench_json"][()])["name"] == "bench"
    for lib in ("velab", "numpy", "scipy", "h5py", "pymodbus", "HDF5"):
        assert r.versions[lib]


def test_format_1_0_manoeuvre_disagreement_is_read_as_the_stored_manoeuvre(tmp_path):
    """A 1.0 file recorded with --beta 10 said 32 in its rig snapshot: read_run now takes the 10."""
    p = tmp_path / "old.h5"
    rig = load_rig("perugia")
    w = RunWriter(p, rig, sample_rate_hz=100.0, swmr=False)
    w.append(np.arange(20) / 100.0, head=np.full(20, 30.0))
    w.close()
    with h5py.File(p, "r+") as fh:  # make it look like a 1.0 recording
        fh.attrs["format_version"] = "1.0"
        fh["entry/manoeuvre/beta"][()] = 10.0
        del fh["entry/sample/rig_json"]
        fh["entry/sample"].attrs["rig_json"] = json.dumps(rig.to_dict())
    assert read_run(p).rig.manoeuvre.beta_per_s == 10.0


def test_synth_with_beta_says_it_once(tmp_path):
    p = tmp_path / "b.h5"
    assert main(["synth", "--beta", "12", "--duration", "1", "-o", str(p)]) == 0
    r = read_run(p)
    assert r.rig.manoeuvre.beta_per_s == 12.0 and r.manoeuvre["beta"] == 12.0


def test_info_json_is_strict(files, capsys):
    capsys.readouterr()
    assert main(["info", "--json", str(files["recorded"])]) == 0
    doc = json.loads(capsys.readouterr().out)  # strict: no NaN (noise_std_m is NaN in the file)
    assert doc["status"] == "completed" and doc["manoeuvre"]["beta"] > 0
    assert "online" in doc["fits"] and doc["fits"]["online"]["models"][0]["name"] == "EL"
    assert doc["noise_std_m"] is None
