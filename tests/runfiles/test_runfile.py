"""Run files: round trips, NeXus discoverability, streaming + SWMR, bad files."""

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time

import h5py
import numpy as np
import pytest

from velab.cli import main
from velab.config import load_material, load_rig
from velab.errors import DataError
from velab.model import valve_head
from velab.runfiles.atomic import edit_copy
from velab.runfiles.reader import read_run
from velab.runfiles.writer import HEAD, Channel, RunWriter, write_run
from velab.synth import with_valve_law


@pytest.fixture(scope="module")
def synth_run(tmp_path_factory):
    path = tmp_path_factory.mktemp("runs") / "a.h5"
    # linear friction, the sigmoid imposed as the flow: the paper's synthetic experiment, made by the
    # frequency-domain model
    assert main(["synth", "--material", "A", "--noise", "0", "--duration", "5", "--pretrigger", "0.5",
                 "--friction", "linear", "--valve", "imposed", "-o", str(path)]) == 0
    return path


def test_synth_noise_free_is_the_model(synth_run):
    r = read_run(synth_run)
    rig, mat = with_valve_law(load_rig("perugia").with_changes(friction="linear"), "imposed"), load_material("A")
    assert r.status == "synthetic"
    assert r.sample_rate_hz == 1000.0
    assert r.time_s[0] == pytest.approx(-0.5) and r.time_s[-1] == pytest.approx(4.999)
    np.testing.assert_allclose(r.head_perturbation(), valve_head(r.time_s, rig, mat), atol=1e-9)
    assert r.steady_head_m == pytest.approx(rig.steady_head_m)
    assert r.material == mat and r.rig == rig
    assert r.noise_std_m == 0.0


def test_synth_noise_is_seeded_and_shared_between_materials(tmp_path):
    paths = {}
    for mat in ("A", "B"):
        paths[mat] = tmp_path / f"{mat}.h5"
        assert main(["synth", "--material", mat, "--duration", "2", "--pretrigger", "0", "--friction", "linear",
                     "--valve", "imposed", "-o", str(paths[mat])]) == 0
    rig = with_valve_law(load_rig("perugia").with_changes(friction="linear"), "imposed")
    ra, rb = read_run(paths["A"]), read_run(paths["B"])
    na = ra.head_m - rig.steady_head_m - valve_head(ra.time_s, rig, load_material("A"))
    nb = rb.head_m - rig.steady_head_m - valve_head(rb.time_s, rig, load_material("B"))
    np.testing.assert_allclose(na, nb, atol=1e-9)  # the same noise for both, as in the paper
    assert np.std(na) == pytest.approx(0.1, rel=0.05)
    assert abs(np.mean(na)) < 0.01


def test_nexus_attributes_alone_lead_to_the_signal(synth_run):
    """A generic reader follows @default and @signal/@axes and finds units everywhere."""
    with h5py.File(synth_run, "r") as f:
        entry = f[f.attrs["default"]]
        assert entry.attrs["NX_class"] == "NXentry"
        data = entry[entry.attrs["default"]]
        assert data.attrs["NX_class"] == "NXdata"
        signal = data[data.attrs["signal"]]
        axis = data[data.attrs["axes"][0]]
        assert signal.attrs["units"] == "m" and axis.attrs["units"] == "s"
        assert signal.shape == axis.shape == (5500,)
        assert signal.chunks is not None and signal.maxshape == (None,)
        for name in ("title", "start_time", "end_time", "status"):
            assert name in entry
        # every dataset with numbers carries units (strings and index tables excepted)
        missing = []

        def visit(name, obj):
            if isinstance(obj, h5py.Dataset) and obj.dtype.kind in "fi" and "units" not in obj.attrs:
                missing.append(name)

        f.visititems(visit)
        assert missing == []
        assert entry["sample/material/tau"].attrs["units"] == "s"
        np.testing.assert_allclose(entry["sample/material/tau"][()], [2, 0.2, 0.02])
        assert f.attrs["format_version"] == "2.0"
        assert json.loads(entry["sample/rig_json"][()])["pipe"]["length_m"] == 102.58


@pytest.mark.skipif(shutil.which("h5dump") is None, reason="h5dump (Debian hdf5-tools) not installed")
def test_h5dump_reads_the_run(synth_run):
    out = subprocess.run(["h5dump", "-H", str(synth_run)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert 'GROUP "entry"' in out.stdout and 'DATASET "head"' in out.stdout


def test_import_round_trip_keeps_values_and_units(tmp_path):
    rig = load_rig("perugia")
    t = np.arange(-200, 800) * 0.002
    p_bar = 3.4 + 0.5 * np.sin(2 * np.pi * 1.7 * t) * (t >= 0)
    csv = tmp_path / "rec.csv"
    with open(csv, "w") as fh:
        fh.write("time_s,p_bar\n")
        for a, b in zip(t, p_bar):
            fh.write(f"{float(a)!r},{float(b)!r}\n")
    out = tmp_path / "rec.h5"
    assert main(["import", str(csv), "--rig", "perugia", "--units", "bar", "--trigger", "0.1", "-o", str(out)]) == 0
    r = read_run(out)
    assert r.status == "imported"
    assert r.sample_rate_hz == pytest.approx(500.0)
    np.testing.assert_allclose(r.time_s, t - 0.1, atol=1e-12)
    np.testing.assert_allclose(r.head_m, p_bar * 1e5 / (rig.fluid.density_kg_m3 * 9.81), rtol=1e-12)
    # the steady head is the mean before the trigger instant (t < 0.1 s on the file's axis)
    expected = np.mean(p_bar[t < 0.1 - 1e-9]) * 1e5 / (rig.fluid.density_kg_m3 * 9.81)
    assert r.steady_head_m == pytest.approx(expected, rel=1e-12)
    assert r.source["units"] == "bar" and r.source["trigger_s"] == 0.1


@pytest.mark.parametrize(
    "body, message",
    [
        ("time,head\n0,1\n0.001,abc\n", "line 3: column 'head': not a number: 'abc'"),
        ("time,head\n" + "".join(f"{i*0.001},1\n" for i in range(12)) + "0.012,nan\n", "line 14: column 'head': nan is not a finite"),
        ("time,head\n" + "".join(f"{i*0.001},1\n" for i in range(12)) + "0.005,1\n", "line 14: time 0.005 s does not increase"),
        ("time,head\n" + "".join(f"{i*0.001},1\n" for i in range(12)) + "0.02,1\n", "line 14: uneven sampling"),
        ("time,head\n0,1\n0.001,1\n", "too few samples (2"),
        ("0,1\n0.001,1\n", "line 1: expected a header row"),
        ("time,head\n" + "".join(f"{i*0.001},1\n" for i in range(12)) + "0.012\n", "line 14: expected 2 columns, found 1"),
    ],
)
def test_malformed_csv_one_line_with_line_number(tmp_path, capsys, body, message):
    csv = tmp_path / "bad.csv"
    csv.write_text(body)
    out = tmp_path / "bad.h5"
    rc = main(["import", str(csv), "--rig", "perugia", "-o", str(out)])
    err = capsys.readouterr().err
    assert rc == 2
    assert message in err and err.count("\n") == 1, err
    assert not out.exists()


def test_existing_run_is_never_overwritten(synth_run, capsys):
    before = synth_run.read_bytes()
    rc = main(["synth", "-o", str(synth_run)])
    assert rc == 2 and "already exists" in capsys.readouterr().err
    assert synth_run.read_bytes() == before


@pytest.mark.parametrize("kind", ["missing", "text", "truncated", "foreign"])
def test_bad_run_files_one_line(tmp_path, synth_run, capsys, kind):
    p = tmp_path / "bad.h5"
    if kind == "text":
        p.write_text("not hdf5")
    elif kind == "truncated":
        data = synth_run.read_bytes()
        p.write_bytes(data[: len(data) // 3])
    elif kind == "foreign":
        with h5py.File(p, "w") as f:
            f["x"] = np.arange(3)
    rc = main(["info", str(p)])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "Traceback" not in err
    assert {"missing": "no such file", "text": "not an HDF5 file", "truncated": "HDF5",
            "foreign": "not a velab run file"}[kind] in err


def test_info_summarises(synth_run, capsys):
    assert main(["info", str(synth_run)]) == 0
    out = capsys.readouterr().out
    assert "status       synthetic" in out and "material     A (S3, truth)" in out
    assert "5500 at 1000 Hz" in out and "fits         none" in out


def test_fit_window_errors(synth_run):
    r = read_run(synth_run)
    t, h = r.fit_window(2.0)
    assert t.size == 2000 and t[0] == pytest.approx(0.0)
    with pytest.raises(DataError, match="longer than the record"):
        r.fit_window(6.0)
    r.head_m[1200] = np.nan
    with pytest.raises(DataError, match="NaN at t = 0.7"):
        r.fit_window(2.0)


def test_fits_group_touches_only_fits(synth_run, tmp_path):
    p = tmp_path / "copy.h5"
    shutil.copy(synth_run, p)
    before = read_run(p)
    with edit_copy(p) as fh:  # the copy-and-rename edit that save_fit makes
        fg = fh["entry"].require_group("fits").create_group("trial")
        fg.attrs["method"] = "x"
    after = read_run(p)
    assert after.fit_names == ["trial"]
    np.testing.assert_array_equal(before.head_m, after.head_m)
    np.testing.assert_array_equal(before.time_s, after.time_s)


WRITER = textwrap.dedent(
    """
    import sys, time, numpy as np
    from velab.runfiles.writer import RunWriter, Channel, HEAD
    from velab.config import load_rig
    w = RunWriter(sys.argv[1], load_rig("perugia"), sample_rate_hz=1000.0,
                  channels=(HEAD, Channel("valve_position", "1")), title="stream")
    i = 0
    while True:
        t = (np.arange(100) + i) / 1000.0
        w.append(t, head=30 + t, valve_position=np.ones(100))
        i += 100
        w.flush()
        print(i, flush=True)
        time.sleep(0.005)
    """
)


def test_swmr_reader_follows_a_live_writer_and_survives_sigkill(tmp_path):
    path = tmp_path / "live.h5"
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(path)], stdout=subprocess.PIPE, text=True)
    try:
        flushed = 0
        while flushed < 2000:
            flushed = int(proc.stdout.readline())
        live = read_run(path)  # opened while the writer holds it in SWMR mode
        assert live.incomplete and live.n_samples >= 2000
        np.testing.assert_allclose(live.head_m, 30 + live.time_s)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        last = flushed
        for line in proc.stdout:
            last = int(line)
    finally:
        if proc.poll() is None:
            proc.kill()
    r = read_run(path)
    assert r.incomplete
    assert r.n_samples >= last  # everything flushed before the kill is there
    np.testing.assert_allclose(r.head_m, 30 + r.time_s)
    assert r.channels["valve_position"].size == r.n_samples
    rc = main(["info", str(path)])
    assert rc == 0


def test_writer_events_gaps_and_close_status(tmp_path):
    path = tmp_path / "w.h5"
    rig = load_rig("perugia")
    w = RunWriter(path, rig, sample_rate_hz=100.0, channels=(HEAD, Channel("raw", "counts", "i4", group="instrument/pressure_transducer")),
                  slow_channels=(Channel("flow", "m^3/s"),), trigger_time_s=0.0)
    w.append(np.arange(-10, 10) / 100.0, head=np.full(20, 30.0), raw=np.arange(20))
    w.gap(20, 5)
    w.append(np.arange(15, 30) / 100.0, head=np.full(15, 31.0), raw=np.arange(15))
    w.append_slow("flow", [0.0, 0.5], [3.6e-3, 3.5e-3])
    w.event(0.0, "trigger", "sigmoid beta 32 gamma -5.5")
    w.close("aborted", "pressure ceiling")
    r = read_run(path)
    assert r.status == "aborted" and r.status_reason == "pressure ceiling"
    assert r.gaps == [(20, 5)]
    assert r.events == [(0.0, "trigger", "sigmoid beta 32 gamma -5.5")]
    assert r.channels["raw"].dtype.kind == "i" and r.channel_units["raw"] == "1"  # ADC counts: a UDUNITS count
    with h5py.File(path, "r") as f:
        np.testing.assert_allclose(f["entry/instrument/flow/value"][()], [3.6e-3, 3.5e-3])
    with pytest.raises(DataError, match="5 samples lost before t = 0.15"):
        r.fit_window(0.3)


def test_synth_matches_the_independent_moc_solver(synth_run):
    """`velab synth --noise 0` is the paper's material A signal: an independent
    method-of-characteristics solution agrees to 1e-3 of the Joukowsky head."""
    from velab.moc import moc_valve_head

    r = read_run(synth_run)
    rig, mat = with_valve_law(load_rig("perugia").with_changes(friction="linear"), "imposed"), load_material("A")
    t_moc, h_moc = moc_valve_head(rig, mat, 5.0, 1e-3)
    after = r.time_s >= 0
    h_synth = np.interp(t_moc, r.time_s[after], r.head_perturbation()[after])
    keep = t_moc <= r.time_s[-1]
    err = np.abs(h_synth[keep] - h_moc[keep]).max()
    assert err < 1e-3 * rig.joukowsky_head_m(mat.wave_speed_m_s)
    # and the first surge is the viscoelastic (lower than Joukowsky) peak
    assert 16.5 < r.head_perturbation().max() < rig.joukowsky_head_m()


KILLED = textwrap.dedent(
    """
    import os, signal, sys
    from velab.runfiles import RunWriter, read_run
    r = read_run(sys.argv[1])
    w = RunWriter(sys.argv[2], r.rig, sample_rate_hz=r.sample_rate_hz, title="killed mid-run")
    w.append(r.time_s, head=r.head_m)
    w.flush()
    os.kill(os.getpid(), signal.SIGKILL)
    """
)


def test_killed_run_is_fitted_and_recovered_into_a_closed_copy(synth_run, tmp_path, capsys):
    killed = tmp_path / "killed.h5"
    proc = subprocess.run([sys.executable, "-c", KILLED, str(synth_run), str(killed)], timeout=60)
    assert proc.returncode == -signal.SIGKILL
    before = killed.read_bytes()
    # saving into the flagged file is refused before any fit: one line, exit 5 (docs/cluster.md), untouched
    assert main(["fit", str(killed), "--models", "0-1", "--window", "2"]) == 5
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "still open for writing" in err and "velab recover" in err
    assert killed.read_bytes() == before
    # fitting what is there works with --no-save, which says so
    assert main(["fit", str(killed), "--models", "0-1", "--window", "2", "--no-save"]) == 0
    out = capsys.readouterr().out
    assert "best model" in out and "open for writing: fitted with --no-save" in out
    assert killed.read_bytes() == before
    # velab recover: a closed copy that takes the fit; the original is untouched
    assert main(["recover", str(killed)]) == 0
    copy = tmp_path / "killed.recovered.h5"
    assert killed.read_bytes() == before
    assert main(["fit", str(copy), "--models", "0-1", "--window", "2"]) == 0
    assert "saved as /entry/fits/" in capsys.readouterr().out
    r, src = read_run(copy), read_run(synth_run)
    assert r.incomplete and "recovered copy of killed.h5" in r.status_reason
    np.testing.assert_array_equal(r.head_m, src.head_m)
    assert r.fit_names
    assert main(["info", str(copy)]) == 0
    assert "INCOMPLETE" in capsys.readouterr().out
    assert main(["recover", str(killed)]) == 2  # never overwrites
    assert "already exists" in capsys.readouterr().err


def test_force_replaces_only_once_the_new_run_is_complete(synth_run, tmp_path, capsys):
    """--force must not delete the old run before the new one exists: a failing import
    (malformed CSV) leaves it as it was; a good one replaces it."""
    target = tmp_path / "run.h5"
    shutil.copy(synth_run, target)
    before = target.read_bytes()
    bad = tmp_path / "bad.csv"
    bad.write_text("time,head\n0,1\n0.001,oops\n")
    assert main(["import", str(bad), "--rig", "perugia", "--force", "-o", str(target)]) == 2
    assert "line 3" in capsys.readouterr().err
    assert target.read_bytes() == before
    good = tmp_path / "good.csv"
    good.write_text("time,head\n" + "".join(f"{i * 0.001 - 0.005},30\n" for i in range(20)))
    assert main(["import", str(good), "--rig", "perugia", "--force", "-o", str(target)]) == 0
    assert read_run(target).status == "imported"
