"""Several transducers through velab synth (one head channel each) and velab import (one column each), and
a fit of the run file with every section."""

from pathlib import Path

import numpy as np
import pytest

from velab.cli import main
from velab.fitting.sections import fit_run_sections
from velab.runfiles import read_run

ROOT = Path(__file__).resolve().parents[1]
TWO = '\n[[transducers]]\nname = "valve"\nposition_m = 102.58\n\n[[transducers]]\nname = "mid"\nposition_m = 41.032\n'


@pytest.fixture(scope="module")
def two(tmp_path_factory):
    d = tmp_path_factory.mktemp("sections")
    rig = d / "two.toml"
    rig.write_text((ROOT / "configs" / "rigs" / "perugia.toml").read_text() + TWO)
    run = d / "two.h5"
    assert main(["synth", "--rig", str(rig), "--duration", "6", "-o", str(run)]) == 0
    return d, rig, run


def test_synth_writes_one_head_channel_per_transducer(two):
    d, rig, path = two
    r = read_run(path)
    assert [s.name for s in r.rig.sections] == ["valve", "mid"]
    mid = r.channels["head_mid"]
    assert mid.shape == r.head_m.shape and r.channel_units["head_mid"] == "m"
    pre = r.time_s < 0
    # its own steady head (the loss up to 40 % of the pipe) and its own noise
    assert np.mean(mid[pre]) == pytest.approx(r.rig.steady_head_at_m(41.032), abs=0.02)
    assert 0.08 < np.std(mid[pre]) < 0.12 and abs(np.corrcoef(mid[pre], r.head_m[pre])[0, 1]) < 0.1
    # the wave reaches mid-pipe (L - x)/a after the valve: its surge starts later
    first = lambda h: r.time_s[np.argmax(h - np.mean(h[pre]) > 1.0)]  # noqa: E731
    assert first(mid) - first(r.head_m) == pytest.approx((102.58 - 41.032) / 353.73, abs=0.01)


def test_each_head_channel_names_its_transducer_and_position(two):
    # the same attributes as a recording's (velab.runfiles.writer.RunWriter writes both)
    import h5py

    _, _, path = two
    with h5py.File(path, "r") as fh:
        data = fh["entry/data"]
        assert [(data[c].attrs["transducer"], float(data[c].attrs["position_m"])) for c in ("head", "head_mid")] == [
            ("valve", 102.58), ("mid", 41.032)]


def _csv(path, r, names):
    with open(path, "w") as fh:
        fh.write(",".join(["time", *names]) + "\n")
        for i in range(r.time_s.size):
            fh.write(f"{r.time_s[i]:.6f},{r.head_m[i]:.6f},{r.channels['head_mid'][i]:.6f}\n")


@pytest.mark.parametrize("names, options", [(["valve", "mid"], []),
                                            (["H1", "H2"], ["--head-column", "valve=H1", "--head-column", "mid=H2"])])
def test_import_takes_one_column_per_transducer(two, names, options):
    d, rig, path = two
    r = read_run(path)
    csv = d / f"{names[0]}.csv"
    _csv(csv, r, names)
    out = d / f"{names[0]}.h5"
    assert main(["import", str(csv), "--rig", str(rig), "-o", str(out), *options]) == 0
    back = read_run(out)
    np.testing.assert_allclose(back.head_m, r.head_m, atol=1e-6)
    np.testing.assert_allclose(back.channels["head_mid"], r.channels["head_mid"], atol=1e-6)
    assert back.source["head_columns"] == {"valve": names[0], "mid": names[1]}


@pytest.mark.parametrize("options, message", [
    ([], "no pressure (transducer 'valve') column 'valve'"),
    (["--value-column", "H1"], "has 2 transducers (valve, mid)"),
    (["--head-column", "valve=H1", "--head-column", "pipe=H2"], "has no transducer 'pipe'"),
    (["--head-column", "valve"], "expected NAME=COLUMN"),
])
def test_import_errors_are_one_line(two, capsys, options, message):
    d, rig, path = two
    csv = d / "H1.csv"
    if not csv.exists():
        _csv(csv, read_run(path), ["H1", "H2"])
    assert main(["import", str(csv), "--rig", str(rig), "-o", str(d / "x.h5"), *options]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err, err


def test_fit_of_the_run_file_uses_both_sections(two):
    d, rig, path = two
    res = fit_run_sections(read_run(path), 6.0, models="3")
    assert [s["name"] for s in res.sections] == ["valve", "mid"]
    assert abs(res.best.wave_speed_m_s - 353.73) <= 0.5 and not res.warnings
    assert all(0.7 < s["noise_ratio"] < 1.5 for s in res.sections)
    assert res.settings["manoeuvre"]["source"] == "position"  # the synthetic run's valve position channel


def test_velab_fit_of_a_run_with_two_sections(two, capsys):
    """velab fit of the run file: the fit path (velab.fitting.entry.fit_run) takes every section; the JSON
    has `sections`; the reduced models are fitted there too (every search option is the stacked sweep's)."""
    import json

    d, rig, path = two
    assert main(["fit", str(path), "--window", "6", "--models", "3", "--json", "--no-save"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [s["name"] for s in doc["sections"]] == ["valve", "mid"] and doc["method"] == "sections"
    assert doc["adequacy"]["baseline_samples"] > 0 and doc["best"] == "S3"
    assert abs(next(m for m in doc["models"] if m["name"] == "S3")["wave_speed"] - 353.73) < 0.5
    assert main(["fit", str(path), "--window", "6", "--models", "3", "--reduced", "--json", "--no-save"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [(m["name"], m["reduced"]) for m in doc["models"]] == [("S3", False), ("S3r", True)]
    assert doc["method"] == "sections" and doc["settings"]["reduced"] is True


def test_velab_info_shows_a_saved_sections_fit(two, tmp_path, capsys):
    import shutil

    d, rig, path = two
    run = tmp_path / "copy.h5"
    shutil.copy(path, run)
    assert main(["fit", str(run), "--window", "6", "--models", "3", "--name", "two_sections"]) == 0
    capsys.readouterr()
    assert main(["info", str(run)]) == 0
    out = capsys.readouterr().out
    assert "fit two_sections: 2 sections, best S3" in out
    assert "section valve at 102.58 m: n " in out and "section mid at 41.032 m: n " in out
    assert "F/noise " in out and "DISAGREES" not in out
