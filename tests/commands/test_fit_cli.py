"""`velab fit` on run files: JSON schema, fit groups, info, many files, bad inputs."""

import json
import os
import sys

import h5py
import numpy as np
import pytest

from velab.cli import main
from velab.config import load_rig
from velab.runfiles import read_run, write_run
from velab.fitting.report import format_report


@pytest.fixture(scope="module")
def run_a(tmp_path_factory):
    p = tmp_path_factory.mktemp("fit") / "a.h5"
    assert main(["synth", "--material", "A", "--duration", "6", "--seed", "5", "-o", str(p)]) == 0
    return p


def _json(capsys, argv):
    capsys.readouterr()
    code = main(argv)
    out = capsys.readouterr()
    return code, out


def test_fit_json_schema_and_fit_group(run_a, capsys):
    with h5py.File(run_a) as fh:
        head_before = fh["entry/data/head"][()]
    code, out = _json(capsys, ["fit", str(run_a), "--models", "0-3", "--window", "5", "--json"])
    assert code == 0, out.err
    doc = json.loads(out.out)
    assert doc["n"] == 5000 and doc["window"] == pytest.approx(5.0)
    names = [m["name"] for m in doc["models"]]
    assert names == ["EL", "S1", "S2", "S3"]
    assert doc["best"] in names
    for m in doc["models"]:
        for key in ("m", "k", "F", "aic", "delta_aic", "weight", "wave_speed", "elements"):
            assert key in m
        assert len(m["elements"]) == m["m"]
        for el in m["elements"]:
            assert set(el) >= {"E", "eta", "tau", "J"}
            assert el["tau"] == pytest.approx(el["eta"] / el["E"])
    best = min(doc["models"], key=lambda m: m["aic"])
    assert best["name"] == doc["best"] and best["delta_aic"] == 0
    # the fit is stored, the recorded data untouched
    with h5py.File(run_a) as fh:
        assert np.array_equal(fh["entry/data/head"][()], head_before)
        g = fh["entry/fits"][doc["fit_name"]]
        # an NXprocess of datasets (not attributes), one NXcollection per model (docs/run-format.md)
        assert g.attrs["NX_class"] == "NXprocess" and g["n"][()] == 5000
        assert g["best"].asstr()[()] == doc["best"] and g["program"].asstr()[()] == "velab"
        assert list(g["settings/models"][()]) == [0, 1, 2, 3]
        s3 = g["S3"]
        assert s3.attrs["NX_class"] == "NXcollection"
        assert s3["k"][()] == 7 and s3["elements/tau"].shape == (3,) and s3["elements/E"].attrs["units"] == "Pa"
        assert s3["F"][()] == pytest.approx(doc["models"][3]["F"]) and s3["wave_speed"].attrs["units"] == "m/s"
    # re-fitting with another window adds a group; the same settings replace it
    assert main(["fit", str(run_a), "--models", "0-1", "--window", "4", "--json"]) == 0
    assert main(["fit", str(run_a), "--models", "0-1", "--window", "4", "--json"]) == 0
    with h5py.File(run_a) as fh:
        assert sorted(fh["entry/fits"]) == ["auto_w4s", "auto_w5s"]
        g = fh["entry/fits/auto_w4s"]
        assert [k for k in g if "model_index" in g[k].attrs] == ["EL", "S1"]
        assert np.array_equal(fh["entry/data/head"][()], head_before)
    capsys.readouterr()
    assert main(["info", str(run_a)]) == 0
    info = capsys.readouterr().out
    assert "auto_w5s" in info and "auto_w4s" in info


def test_fit_table_and_plot(run_a, tmp_path, capsys):
    png = tmp_path / "report.png"
    code, out = _json(capsys, ["fit", str(run_a), "--models", "0-2", "--window", "5", "--no-save",
                               "--plot", str(png), "-v"])  # (the statistics in full: -v; the default opens with the result)
    assert code == 0
    assert "best model (minimum AIC AR1)" in out.out and "lag-1" in out.out and "n = 5000" in out.out
    assert "bounds: tau in [" in out.out and "+-" in out.out
    assert png.read_bytes()[:4] == b"\x89PNG"


def _nan_run(tmp_path):
    r = read_run_cached()
    head = r.head_m.copy()
    head[r.time_s.searchsorted(1.0)] = np.nan
    p = tmp_path / "nan.h5"
    write_run(p, load_rig("perugia"), r.time_s, head, status="imported", sample_rate_hz=r.sample_rate_hz)
    return p


_CACHE = {}


def read_run_cached():
    return _CACHE["run"]


def test_bad_inputs_one_line_errors(run_a, tmp_path, capsys):
    _CACHE["run"] = read_run(run_a)
    text = tmp_path / "text.h5"
    text.write_text("not an hdf5 file\n")
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as fh:
        fh["x"] = np.arange(3)
    trunc = tmp_path / "trunc.h5"
    data = run_a.read_bytes()
    trunc.write_bytes(data[: len(data) // 2])
    cases = {
        "missing": [str(tmp_path / "nope.h5")],
        "not hdf5": [str(text)],
        "not a run": [str(other)],
        "truncated": [str(trunc)],
        "window": [str(run_a), "--window", "60"],
        "nan": [str(_nan_run(tmp_path)), "--window", "5"],
    }
    for label, args in cases.items():
        capsys.readouterr()
        code = main(["fit", *args, "--models", "0-1", "--no-save"])
        err = capsys.readouterr().err.strip()
        assert code != 0, label
        assert err.startswith("velab: ") and "\n" not in err and "Traceback" not in err, (label, err)


def test_many_files_one_bad(run_a, tmp_path, capsys):
    import shutil

    good = tmp_path / "good.h5"
    shutil.copy(run_a, good)
    bad = tmp_path / "bad.h5"
    bad.write_text("garbage")
    capsys.readouterr()
    code = main(["fit", str(good), str(bad), "--models", "0-1", "--window", "3", "--jobs", "2", "--json"])
    out = capsys.readouterr()
    assert code != 0
    doc = json.loads(out.out)
    by = {r["path"]: r for r in doc["runs"]}
    assert "error" in by[str(bad)] and by[str(good)]["best"] in ("EL", "S1")
    assert str(bad) in out.err
    with h5py.File(good) as fh:
        assert "auto_w3s" in fh["entry/fits"]


def test_bound_options_and_rig_fit_table(run_a, tmp_path, capsys):
    """--tau-min/--tau-max, the rig's [fit] table and their errors; the bounds go into the run file."""
    from velab.config import load_rig
    from velab.rig import rig_from_dict
    from velab.errors import ConfigError

    for bad, msg in ((["--tau-min", "-1"], "--tau-min"), (["--tau-max", "0"], "--tau-max"),
                     (["--tau-min", "0.5", "--tau-max", "0.1"], "--tau-min")):
        capsys.readouterr()
        try:
            code = main(["fit", str(run_a), "--models", "0-1", "--no-save", *bad])
        except SystemExit as exc:  # argparse's own checks
            code = exc.code
        assert code != 0
        err = capsys.readouterr().err.strip()
        assert err.startswith("velab") and msg in err and "\n" not in err and "Traceback" not in err
    capsys.readouterr()
    assert main(["fit", str(run_a), "--models", "0-2", "--window", "5", "--tau-min", "0.005", "--tau-max", "50",
                 "--name", "bounded", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    b = doc["settings"]["bounds"]
    assert (b["tau_min_s"], b["tau_max_s"]) == (0.005, 50.0) and b["sources"]["tau_min_s"] == "option"
    for m in doc["models"]:
        assert isinstance(m["at_bounds"], list) and "wave_speed_se" in m and "aic_ar1" in m
        for el in m["elements"]:
            assert 0.005 * (1 - 1e-9) <= el["tau"] <= 50.0 * (1 + 1e-9)
    from velab.runfiles import read_fit_group

    with h5py.File(run_a) as fh:
        stored = read_fit_group(fh["entry/fits/bounded"])
    assert stored.settings["bounds"]["tau_min_s"] == 0.005 and stored.settings["selection"] == "ar1"
    assert stored.selection == "ar1" and stored.best.name == doc["best"]
    by = {m["name"]: m for m in doc["models"]}
    for f in stored.models:  # the new per-model fields survive the run file
        assert f.at_bounds == by[f.name]["at_bounds"] and f.negligible == tuple(
            el["negligible"] for el in by[f.name]["elements"])
        assert f.wave_speed_se_m_s == pytest.approx(by[f.name]["wave_speed_se"])
    # the rig's [fit] table: validated, carried by the rig (run files store it)
    src = (load_rig("perugia").source)
    text = open(src).read()
    good = tmp_path / "rig.toml"
    good.write_text(text + "\n[fit]\ntau_min_s = 0.004\ntau_max_s = 60.0\n")
    rig = load_rig(good)
    assert (rig.fit.tau_min_s, rig.fit.tau_max_s) == (0.004, 60.0)
    assert rig_from_dict(json.loads(json.dumps(rig.to_dict()))).fit == rig.fit
    for extra, key in (("[fit]\ntau_min_s = -1\n", "[fit] tau_min_s"), ("[fit]\ntau_min_s = 2.0\ntau_max_s = 1.0\n",
                                                                        "[fit] tau_max_s"),
                       ("[fit]\ntau_mn_s = 1.0\n", "[fit] tau_mn_s")):
        bad = tmp_path / "bad.toml"
        bad.write_text(text + "\n" + extra)
        with pytest.raises(ConfigError, match=key.replace("[", r"\[").replace("]", r"\]")):
            load_rig(bad)


def test_result_round_trip_and_old_documents(run_a, capsys):
    from velab.fitting import SweepResult

    capsys.readouterr()
    assert main(["fit", str(run_a), "--models", "0-2", "--window", "4", "--no-save", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    r = SweepResult.from_dict(doc)
    assert r.best.name == doc["best"] and r.selection == "ar1"
    assert r.to_dict()["models"][1]["elements"] == doc["models"][1]["elements"]
    # a document written before these fields existed (white-noise AIC only) still reads
    old = {"n": 10, "window": 1.0, "method": "auto", "models": [
        {"name": "EL", "m": 0, "k": 1, "F": 2.0, "aic": 8.9, "delta_aic": 1.0, "wave_speed": 350.0, "elements": []},
        {"name": "S1", "m": 1, "k": 3, "F": 1.0, "aic": 6.0, "delta_aic": 0.0, "wave_speed": 351.0,
         "elements": [{"E": 1e10, "eta": 1e9, "tau": 0.1, "J": 1e-10}]}]}
    r = SweepResult.from_dict(old)
    assert r.best.name == "S1" and r["S1"].tau_s == pytest.approx((0.1,)) and r["S1"].negligible == (False,)
    assert "S1" in format_report(r)



# the run files opened while a count runs: sys.audit's "open" event (open(), os.open) is the process's own record
# of a file opened, so a test counts reads without patching the reader. (A hook cannot be removed: it stays, idle.)
_OPENED: list | None = None
_HOOKED = False


def _audit(event, args):
    if event == "open" and _OPENED is not None and isinstance(args[0], (str, bytes, os.PathLike)):
        _OPENED.append(os.path.realpath(os.fsdecode(args[0])))


def _opens(paths, call) -> list[int]:
    """How many times this process opens each of ``paths`` during ``call()``."""
    global _OPENED, _HOOKED
    if not _HOOKED:
        sys.addaudithook(_audit)
        _HOOKED = True
    _OPENED = []
    try:
        call()
        return [_OPENED.count(os.path.realpath(p)) for p in paths]
    finally:
        _OPENED = None


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory):
    """Two small runs of one pipe (2 s at 200 Hz): the plumbing of a joint fit, not its science."""
    d = tmp_path_factory.mktemp("joint")
    for seed in (1, 2):
        assert main(["synth", "--material", "A", "--duration", "2", "--rate", "200", "--seed", str(seed),
                     "-o", str(d / f"run{seed}.h5"), "-q"]) == 0
    return [str(d / "run1.h5"), str(d / "run2.h5")]


def test_a_joint_fit_reads_each_run_once(two_runs, tmp_path, capsys):
    """`velab fit A B --joint` reads its runs once (velab.jointfiles.read_sources: checked before the fit), fits
    those (velab.fitservice.execute's ``sources``) and draws the figure from them: each run file is opened as
    often as one read_sources opens it, not twice that."""
    from velab.jointfiles import read_sources

    once = _opens(two_runs, lambda: read_sources(two_runs, 1.5))
    assert all(n > 0 for n in once), once  # (the count sees the reader's opens)
    figure = tmp_path / "joint.png"
    capsys.readouterr()
    fit = _opens(two_runs, lambda: main(["fit", *two_runs, "--joint", "--models", "1", "--window", "1.5",
                                         "--no-save", "--plot", str(figure), "--json"]))
    out = capsys.readouterr()
    assert json.loads(out.out)["paths"] == two_runs, out.err
    assert fit == once and figure.read_bytes()[:4] == b"\x89PNG"


def test_a_joint_fit_takes_the_reduced_models(two_runs, tmp_path, capsys):
    """`velab fit A B --joint --reduced` (the stacked sweep takes every search option, the reduced models too): exit
    0, the JSON lists S1r with its flag after S1, and the fit is saved into both runs under the joint default name
    with "_reduced" (as a single fit's: it does not overwrite the fit without them)."""
    import shutil

    runs = [str(shutil.copy(p, tmp_path / os.path.basename(p))) for p in two_runs]
    capsys.readouterr()
    assert main(["fit", *runs, "--joint", "--reduced", "--models", "1", "--window", "1.5", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [(m["name"], m["reduced"]) for m in doc["models"]] == [("S1", False), ("S1r", True)]
    assert doc["settings"]["reduced"] is True and doc["fit_name"] == "joint_w1.5s_reduced"
    from velab.runfiles.summary import read_fits

    for path in runs:  # (the run file's fit group keeps each model's flag)
        stored = read_fits(path)["joint_w1.5s_reduced"]
        assert [(m["name"], bool(m["reduced"])) for m in stored["models"]] == [("S1", False), ("S1r", True)]


def test_execute_fits_the_runs_it_is_given_only_for_their_request(two_runs):
    """The runs passed to execute must be the request's, in its order: another request's are refused, not fitted."""
    from velab.fitservice.execute import execute
    from velab.fitservice.request import FitRequest, RunFile, RunFiles
    from velab.jointfiles import read_sources

    sources = read_sources(two_runs, 1.5)
    for request in (FitRequest(RunFiles(tuple(reversed(two_runs))), 1.5), FitRequest(RunFile(two_runs[0]), 1.5)):
        with pytest.raises(ValueError, match="not the request's"):
            execute(request, sources=sources)


def test_the_walker_is_started_before_the_fitter_is_imported(two_runs, monkeypatch, capsys):
    """`velab fit` starts the child that walks its run files (velab.runfiles.probe) before it imports the fitter
    (its options' check), when the runs are read in this process: one run, a joint fit, a batch fitted here. Runs
    fitted in fit processes (--jobs N) or on a cluster are walked there: no child here for them."""
    from velab.commands import fit
    from velab.errors import DataError
    from velab.runfiles import probe

    seen = []

    def options(args):
        seen.append(probe._walker)
        raise DataError("stop here")

    monkeypatch.setattr(fit, "_options", options)
    cases = [([two_runs[0]], True), ([*two_runs, "--joint"], True), ([*two_runs, "--jobs", "1"], True),
             ([*two_runs, "--jobs", "2"], os.cpu_count() == 1),
             ([two_runs[0], "--scheduler", "tcp://127.0.0.1:1"], False)]
    for argv, started in cases:
        with probe._lock:
            probe._known.clear()  # (the runs were written by this process: trusted, never walked)
        if probe._walker is not None:
            probe._walker.close()
            probe._walker = None
        seen.clear()
        assert main(["fit", *argv, "--no-save"]) != 0
        assert "stop here" in capsys.readouterr().err
        assert (seen[0] is not None) == started, argv
        if started:
            assert seen[0].owner == os.getpid() and not seen[0].ready  # started, not waited for
