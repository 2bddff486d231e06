"""Issue 52's reproducers, one regression test each: every input checked at the door (velab.bounds).

Each case runs ``velab.cli.main`` in-process and asserts what the issue's acceptance asks: one line
naming what is wrong, a documented exit code, no traceback, within a time limit, and the input
files unchanged (a refused command never modifies a recorded run).
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest

from fuzzing import Hang, time_limit
from velab.cli import main
from velab.configpath import find_config

LIMIT_S = 60.0
DOCUMENTED = {0, 2, 3, 4, 5, 6, 130}


def run_main(argv, limit_s: float = LIMIT_S) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            with time_limit(limit_s):
                code = main([str(a) for a in argv])
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 2
        except Hang:
            pytest.fail(f"velab {' '.join(map(str, argv))} hung")
    return code, out.getvalue(), err.getvalue()


def refused(argv, *words, code: int = 2, files=()) -> str:
    """``velab argv`` ends with exit ``code`` and one line on stderr naming every one of ``words``;
    ``files`` are byte-identical afterwards."""
    before = {f: f.read_bytes() for f in files}
    got, out, err = run_main(argv)
    assert got == code, f"velab {argv} -> {got}\n{out}\n{err}"
    assert "Traceback" not in err and err.count("\n") == 1, err
    for w in words:
        assert w in err, (w, err)
    for f, data in before.items():
        assert f.read_bytes() == data, f"{f} was changed by a refused command"
    return err


RIG_TEXT = find_config("rigs", "perugia").read_text()


def rig_file(tmp_path, old: str, new: str, extra: str = "") -> str:
    assert old in RIG_TEXT
    p = tmp_path / "rig.toml"
    p.write_text(RIG_TEXT.replace(old, new) + extra)
    return str(p)


# ------------------------------------------------------------------ configs


def test_gamma_1e9_refused_by_synth_and_import(tmp_path):
    rig = rig_file(tmp_path, "gamma = -5.5", "gamma = 1e9")
    refused(["synth", "--rig", rig, "-o", tmp_path / "s.h5"], "[manoeuvre] gamma", "must be in")
    csv = tmp_path / "r.csv"
    csv.write_text("time,head\n" + "".join(f"{i / 1000 - 0.005!r},34.7\n" for i in range(50)))
    refused(["import", csv, "--rig", rig, "-o", tmp_path / "i.h5"], "[manoeuvre] gamma")
    assert not list(tmp_path.glob("*.h5"))


def test_beta_1e29_refused_by_import_as_by_synth(tmp_path):
    rig = rig_file(tmp_path, "beta_per_s = 32.0", "beta_per_s = 1e29")
    refused(["synth", "--rig", rig, "-o", tmp_path / "s.h5"], "[manoeuvre] beta_per_s")
    csv = tmp_path / "r.csv"
    csv.write_text("time,head\n" + "".join(f"{i / 1000 - 0.005!r},34.7\n" for i in range(50)))
    refused(["import", csv, "--rig", rig, "-o", tmp_path / "i.h5"], "[manoeuvre] beta_per_s")


def test_material_wave_speed_1e29_refused(tmp_path):
    mat = tmp_path / "m.toml"
    mat.write_text("wave_speed_m_s = 1e29\n")
    refused(["synth", "--material", mat, "-o", tmp_path / "s.h5"], "wave_speed_m_s", "m/s")


def test_misspelt_table_named_with_the_right_one(tmp_path):
    rig = rig_file(tmp_path, "[pipe]\n", "[pipes]\n")
    err = refused(["synth", "--rig", rig, "-o", tmp_path / "s.h5"], "unknown table [pipes] (did you mean [pipe]?)")
    assert "missing table" not in err


def test_unknown_top_level_table_refused_like_an_unknown_key(tmp_path):
    rig = rig_file(tmp_path, "[fluid]", "[fluid]", extra="\n[extra]\nx = 1\n")
    refused(["synth", "--rig", rig, "-o", tmp_path / "s.h5"], "unknown table [extra]")


def test_thousands_of_transducers_refused_at_once(tmp_path):
    many = "".join(f'\n[[transducers]]\nname = "t{i}"\nposition_m = {1 + i * 0.001:.3f}\n' for i in range(19_999))
    rig = rig_file(tmp_path, "[fluid]", "[fluid]", extra=many)
    assert os.path.getsize(rig) < 1 << 20
    t0 = time.monotonic()
    refused(["synth", "--rig", rig, "-o", tmp_path / "s.h5"], "[[transducers]]", "19999")
    assert time.monotonic() - t0 < LIMIT_S


# ------------------------------------------------------------------ CSV imports


def _csv(tmp_path, lines, name="r.csv") -> str:
    p = tmp_path / name
    p.write_text("\n".join(lines) + "\n")
    return str(p)


T = (np.arange(-100, 400) / 1000.0).tolist()
H = (34.7 + 5 * np.sin(30 * np.maximum(np.array(T), 0))).tolist()


@pytest.mark.parametrize("case,lines,words", [
    ("kpa", ["time,head"] + [f"{a!r},{b * 9.81 * 0.9982!r}" for a, b in zip(T, H)], ["kPa", "--units kPa"]),
    ("decimal comma", ["time,head"] + [f"{a:.3f},{b:.3f}".replace(".", ",") for a, b in zip(T, H)],
     ["decimal comma"]),
    ("decimal comma ;", ["time;head"] + [f"{a:.3f};{b:.3f}".replace(".", ",") for a, b in zip(T, H)],
     ["decimal comma"]),
    ("tiny step", ["time,head"] + [f"{i * 1e-300!r},{b!r}" for i, b in enumerate(H)], ["time step", "Hz"]),
    ("NUL", ["time,head"] + [f"{a!r},{b!r}" for a, b in zip(T, H)][:50] + ["0.5\0,3"], ["NUL"]),
    ("head,head,head", ["head,head,head"] + [f"{a!r},{b!r},{b!r}" for a, b in zip(T, H)], ["more than once"]),
    ("extra fields", ["time,head"] + [f"{a!r},{b!r},7" for a, b in zip(T, H)], ["expected 2 columns, found 3"]),
    ("1e308", ["time,head"] + [f"{a!r},1e308" for a in T], ["1e+308", "transducer"]),
    ("1e300 after", ["time,head"] + [f"{a!r},{b * 1e300 if a > 0.1 else b!r}" for a, b in zip(T, H)], ["head"]),
])
def test_bad_csv_refused_in_one_line(tmp_path, case, lines, words):
    csv = _csv(tmp_path, lines)
    refused(["import", csv, "--rig", "perugia", "-o", tmp_path / "out.h5"], csv, *words, files=[tmp_path / "r.csv"])
    assert not (tmp_path / "out.h5").exists()


def test_kpa_csv_imports_with_its_units(tmp_path):
    csv = _csv(tmp_path, ["time,head"] + [f"{a!r},{b * 9.81 * 0.9982!r}" for a, b in zip(T, H)])
    code, out, err = run_main(["import", csv, "--rig", "perugia", "--units", "kPa", "-o", tmp_path / "out.h5"])
    assert code == 0, err


# ------------------------------------------------------------------ run files


@pytest.fixture(scope="module")
def base_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("base")
    p = d / "base.h5"
    code, out, err = run_main(["synth", "--duration", "2", "-o", p])
    assert code == 0, err
    return p


def _damaged(base_run, tmp_path, edit, name="case.h5"):
    p = tmp_path / name
    shutil.copy(base_run, p)
    with h5py.File(p, "r+") as fh:
        edit(fh)
    return p


def _set_status(value):
    def edit(fh):
        del fh["entry/status"]
        fh["entry/status"] = value
    return edit


UNSOUND = {
    "status deleted": (lambda fh: fh["entry"].__delitem__("status"), "no /entry/status"),
    "status bogus": (_set_status("bogus"), "'bogus'"),
    "format_version removed": (lambda fh: fh.attrs.__delitem__("format_version"), "@format_version"),
    "entry NX_class removed": (lambda fh: fh["entry"].attrs.__delitem__("NX_class"), "@NX_class"),
    "root NX_class removed": (lambda fh: fh.attrs.__delitem__("NX_class"), "@NX_class"),
    "signal removed": (lambda fh: fh["entry/data"].attrs.__delitem__("signal"), "@signal"),
    "manoeuvre deleted": (lambda fh: fh["entry"].__delitem__("manoeuvre"), "/entry/manoeuvre"),
}


@pytest.mark.parametrize("case", sorted(UNSOUND))
def test_unsound_run_named_damaged_and_never_written(base_run, tmp_path, case):
    edit, words = UNSOUND[case]
    p = _damaged(base_run, tmp_path, edit)
    code, out, err = run_main(["info", p])
    assert code == 2 and "DAMAGED" in out and err.count("\n") == 1 and words in err, (out, err)
    code, out, _ = run_main(["info", "--json", p])
    assert code == 2 and words in json.loads(out)["damaged"]
    refused(["fit", p, "--models", "0", "--window", "1"], "damaged run", words, "--no-save", files=[p])


def test_unsound_run_fits_with_no_save_saying_so(base_run, tmp_path):
    p = _damaged(base_run, tmp_path, UNSOUND["manoeuvre deleted"][0])
    before = p.read_bytes()
    code, out, err = run_main(["fit", p, "--models", "0", "--window", "1", "--no-polish", "--starts", "1",
                               "--no-save"])
    assert code == 0, err
    assert "damaged" in err and "--no-save" in err and "nothing written" in out
    assert p.read_bytes() == before


def _rig_json(edit):
    def apply(fh):
        d = json.loads(fh["entry/sample/rig_json"][()])
        edit(d)
        del fh["entry/sample/rig_json"]
        fh["entry/sample/rig_json"] = json.dumps(d)
    return apply


def _complex_head(fh):
    h = fh["entry/data/head"][()]
    attrs = dict(fh["entry/data/head"].attrs)
    del fh["entry/data/head"]
    ds = fh["entry/data"].create_dataset("head", data=h.astype(complex))
    ds.attrs.update(attrs)


def _huge_head(fh):
    fh["entry/data/head"][5] = 1e300


BAD_VALUES = {
    "beta -32": (lambda fh: fh["entry/manoeuvre/beta"].__setitem__((), -32.0), "/entry/manoeuvre/beta"),
    "negative length": (_rig_json(lambda d: d["pipe"].__setitem__("length_m", -102.58)), "[pipe] length_m"),
    "wave speed 1e29": (_rig_json(lambda d: d.__setitem__("nominal_wave_speed_m_s", 1e29)), "nominal_speed_m_s"),
    "complex head": (_complex_head, "complex"),
    "head 1e300": (_huge_head, "head 1e+300"),
}


@pytest.mark.parametrize("case", sorted(BAD_VALUES))
def test_run_with_non_physical_values_refused_by_info_and_fit(base_run, tmp_path, case):
    edit, words = BAD_VALUES[case]
    p = _damaged(base_run, tmp_path, edit)
    refused(["info", p], words, files=[p])
    refused(["fit", p, "--models", "0", "--window", "1"], words, files=[p])
    refused(["fit", p, "--models", "0", "--window", "1", "--no-save"], words, files=[p])


KILLED = """
import os, signal, sys
import numpy as np
from velab.runfiles import read_run, RunWriter
r = read_run(sys.argv[1])
w = RunWriter(sys.argv[2], r.rig, sample_rate_hz=r.sample_rate_hz, title="live")
w.append(r.time_s, head=r.head_m)
w.flush()
print("ready", flush=True)
sys.stdin.readline()
"""


def test_fit_of_a_run_being_recorded_is_one_line_exit_5(base_run, tmp_path):
    live = tmp_path / "live.h5"
    proc = subprocess.Popen([sys.executable, "-c", KILLED, str(base_run), str(live)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        refused(["fit", live, "--models", "0", "--window", "1"], "still open for writing", code=5)
    finally:
        proc.stdin.close()
        proc.wait(timeout=60)


# ------------------------------------------------------------------ CLI arguments and signals


def test_runs_best_unknown_model_refused(tmp_path):
    refused(["runs", tmp_path, "--best", "S99"], "--best S99")


def test_sigterm_during_synth_exits_130_without_a_partial_file(tmp_path):
    out = tmp_path / "s.h5"
    proc = subprocess.Popen([sys.executable, "-m", "velab.cli", "-v", "synth", "--duration", "1200", "-o", str(out)],
                            stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    first = proc.stderr.readline()  # -v: "synthesising ..." once the model run starts
    assert "synthesising" in first, first
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, (proc.returncode, err)
    assert "Traceback" not in err and err.strip() == "velab: terminated (SIGTERM)", err
    assert not list(tmp_path.glob(".*part")) and not out.exists()
