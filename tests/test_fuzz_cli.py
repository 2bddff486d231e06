"""Property-based tests of the CLI parser and the light commands, run in-process through velab.cli.main.

* Every numeric option carries a domain (velab.commands.common.Number); a value just outside
  it (NaN, inf, out of range, not a number) is refused by argparse: exit 2, one line, nothing run.
* Random argv for every subcommand never gives a traceback or a hang; for the commands that
  only read files (info, recover, fit, import) random argv is also executed, with file
  arguments drawn from a pool of bad files: exit 0 would be nonsense accepted.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os

import pytest
from hypothesis import given
from hypothesis import strategies as st

from fuzzing import Hang, time_limit
from velab.cli import build_parser, main
from velab.commands.common import Number

pytestmark = pytest.mark.timeout(900)

# commands that start devices or windows are parsed here, never run.
RUNNABLE = {"info", "recover", "fit", "import"}
LIMIT_S = 20.0


def subparsers() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


SUBS = subparsers()


def options(sub: argparse.ArgumentParser):
    return [a for a in sub._actions if a.option_strings and not isinstance(a, argparse._HelpAction)]


def test_every_numeric_option_has_a_domain():
    untyped = []
    for name, sub in SUBS.items():
        for a in options(sub):
            if a.type in (int, float) or (a.type is not None and not isinstance(a.type, Number)
                                          and getattr(a.type, "__name__", "") in ("positive_float", "non_negative_float")):
                untyped.append(f"velab {name} {a.option_strings[-1]}")
    assert not untyped, f"numeric options without a domain: {untyped}"


def run_main(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            with time_limit(LIMIT_S):
                code = main(argv)
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 2
        except Hang:
            pytest.fail(f"velab {' '.join(argv)} hung")
    return code, out.getvalue(), err.getvalue()


def out_of_domain(t: Number) -> list[str]:
    bad = ["nan", "inf", "-inf", "1e999", "abc", "", "0x10"]
    if t.kind is int:
        bad += ["1.5", "1e3"]
    span = max(1.0, abs(t.hi - t.lo) if t.lo is not None and t.hi is not None else 1.0)
    if t.lo is not None:
        bad.append(repr(t.lo) if t.lo_open else repr(t.lo - (1 if t.kind is int else span * 1e-3)))
    if t.hi is not None:
        bad.append(repr(t.hi) if t.hi_open else repr(t.hi + (1 if t.kind is int else span * 1e-3)))
    return [str(int(float(b))) if t.kind is int and b.lstrip("-").replace(".", "").isdigit() and float(b).is_integer()
            else b for b in bad]


def minimal_args(name: str, sub: argparse.ArgumentParser, tmp) -> list[str]:
    """The positionals and required options of a subcommand, with harmless values."""
    argv = []
    for a in sub._actions:
        if not a.option_strings and a.dest != "help" and not isinstance(a, argparse._SubParsersAction):
            argv.append(a.choices[0] if a.choices else str(tmp / "missing.h5"))
        elif a.option_strings and a.required:
            argv += [a.option_strings[-1], "perugia" if "rig" in a.dest else str(tmp / "out.h5")]
    return argv


DOMAIN_CASES = [(name, a.option_strings[-1], a.type) for name, sub in SUBS.items()
                for a in options(sub) if isinstance(a.type, Number)]


def test_domain_cases_cover_every_command_with_numbers():
    assert {"synth", "fit", "import", "sim", "record", "valve"} <= {c[0] for c in DOMAIN_CASES}


@given(case=st.sampled_from(DOMAIN_CASES), data=st.data())
def test_out_of_domain_values_are_refused(case, data, tmp_path_factory):
    name, opt, typ = case
    bad = data.draw(st.sampled_from(out_of_domain(typ)))
    tmp = tmp_path_factory.mktemp("cli")
    argv = [name, *minimal_args(name, SUBS[name], tmp), f"{opt}={bad}"]
    code, out, err = run_main(argv)
    assert code == 2, f"velab {' '.join(argv)} -> {code}\n{err}"
    assert err.count("\n") == 1 and opt in err and "Traceback" not in err, err
    assert not any(tmp.iterdir()), "a refused command wrote something"


@pytest.fixture(scope="module")
def bad_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("pool")
    (d / "empty.h5").write_bytes(b"")
    (d / "junk.h5").write_bytes(os.urandom(4096))
    (d / "text.csv").write_text("time,head\n")
    (d / "rig.toml").write_text("[pipe]\nlength_m = -1\n")
    # corrupt HDF5 files (a valid signature, broken structure) are the run-file reader's own fuzz target
    return [str(d / n) for n in ("empty.h5", "junk.h5", "text.csv", "rig.toml", "none.h5")] + [
        str(d), "/dev/zero", "/dev/null"]


VALUE_TOKENS = st.one_of(
    st.sampled_from(["0", "-1", "1", "1e9", "nan", "inf", "-0", "20", "0-6", "1,3", "S3", "auto", "perugia", "A",
                     "m", "bar", "x.png", "nodir/x.png", "/", "", "=", "--", "-"]),
    st.text(alphabet=st.characters(blacklist_categories=("Cs",), blacklist_characters="\0"), max_size=8),
)


@given(data=st.data())
def test_random_argv_never_tracebacks(data, bad_files, tmp_path_factory):
    name = data.draw(st.sampled_from(sorted(SUBS)))
    sub = SUBS[name]
    opts = [s for a in options(sub) for s in a.option_strings if s not in ("--version",)]
    token = st.one_of(st.sampled_from(opts or ["--help"]), VALUE_TOKENS, st.sampled_from(bad_files))
    argv = [name] + data.draw(st.lists(token, max_size=8))
    if "-h" in argv or "--help" in argv:
        argv = [a for a in argv if a not in ("-h", "--help")]
    tmp = tmp_path_factory.mktemp("argv")
    # parse only: nothing is started
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            with time_limit(LIMIT_S):
                build_parser().parse_args(argv)
            parsed = True
        except SystemExit as exc:
            assert exc.code == 2, exc.code
            parsed = False
    assert "Traceback" not in err.getvalue()
    if not parsed:
        assert err.getvalue().count("\n") == 1, err.getvalue()
        return
    if name not in RUNNABLE or "--log-file" in argv:
        return
    cwd = os.getcwd()
    os.chdir(tmp)  # relative outputs land in a temp dir
    try:
        code, out, errtext = run_main(argv)
    finally:
        os.chdir(cwd)
    assert "Traceback" not in errtext
    # every file in the pool is bad input (no run, no CSV, no rig): success would be nonsense
    assert code != 0, f"velab {' '.join(argv)} exited 0:\n{out}"
    assert code in (2, 5), (code, errtext)


# ------------------------------------------------------------------ mutated inputs through the entry points
# Issue 52: mutated run files through `velab info` and `velab fit` (saving: a refusal comes before the fit, and
# a sound mutant is fitted cheaply), mutated CSVs and rigs through `velab import`. Each: one line on stderr when
# refused, a documented exit code, within the time limit, the input files unchanged. The budget is short in the
# suite (FUZZ_ENTRY examples); VELAB_FUZZ_EXAMPLES raises it for a longer hunt (docs/cli.md).

from hypothesis import settings  # noqa: E402

DOCUMENTED = {0, 2, 3, 4, 5, 6, 130}
ENTRY_BUDGET = settings(max_examples=int(os.environ.get("VELAB_FUZZ_EXAMPLES", "12")), deadline=None)


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    p = tmp_path_factory.mktemp("run") / "base.h5"
    code, _, err = run_main(["synth", "--duration", "1", "--pretrigger", "0.2", "-o", str(p)])
    assert code == 0, err
    return p


def _check_outcome(argv, code, out, err, files_before):
    assert "Traceback" not in err, err
    assert code in DOCUMENTED, (argv, code, err)
    if code != 0:
        lines = [ln for ln in err.splitlines() if ln.startswith("velab: ") and "warning" not in ln]
        assert len(lines) >= 1 and all("\n" not in ln for ln in lines), err
    for f, data in files_before.items():
        if code != 0 or "--no-save" in argv or argv[0] != "fit":
            assert f.read_bytes() == data, f"velab {' '.join(argv)} changed {f}"


_RUN_EDITS = ["delete", "attr_delete", "scale", "retype", "status"]
_RUN_PATHS = ["entry/status", "entry/manoeuvre", "entry/manoeuvre/beta", "entry/manoeuvre/gamma", "entry/data/head",
              "entry/data/time", "entry/sample/rig_json", "entry/data/flow", "entry/title"]
_RUN_ATTRS = [("/", "format_version"), ("/", "NX_class"), ("entry", "NX_class"), ("entry/data", "signal"),
              ("entry/data", "NX_class"), ("entry/data/time", "sample_rate_hz")]


@ENTRY_BUDGET
@given(ops=st.lists(st.tuples(st.sampled_from(_RUN_EDITS), st.integers(0, 50),
                              st.sampled_from([-1e300, -32.0, 0.0, 1e-300, 1e9, 1e29, float("nan")])),
                    min_size=1, max_size=3),
       command=st.sampled_from(["info", "info --json", "fit"]))
def test_mutated_run_files_through_info_and_fit(small_run, tmp_path_factory, ops, command):
    import json as _json
    import shutil

    import h5py
    import numpy as np

    case = tmp_path_factory.mktemp("mut") / "case.h5"
    shutil.copy(small_run, case)
    with h5py.File(case, "r+") as fh:
        for op, i, value in ops:
            path = _RUN_PATHS[i % len(_RUN_PATHS)]
            obj, attr = _RUN_ATTRS[i % len(_RUN_ATTRS)]
            try:
                if op == "delete" and path in fh:
                    del fh[path]
                elif op == "attr_delete" and obj in fh and attr in fh[obj].attrs:
                    del fh[obj].attrs[attr]
                elif op == "scale" and path in fh and isinstance(fh[path], h5py.Dataset) and fh[path].dtype.kind == "f":
                    ds = fh[path]
                    if ds.shape == ():
                        ds[()] = value
                    else:
                        ds[i % ds.shape[0]] = value
                elif op == "retype" and path in fh and isinstance(fh[path], h5py.Dataset) and fh[path].shape != ():
                    data = fh[path][()]
                    del fh[path]
                    fh[path] = data.astype(complex) if data.dtype.kind == "f" else data
                elif op == "status" and "entry/status" in fh:
                    del fh["entry/status"]
                    fh["entry/status"] = "bogus" if i % 2 else "completed"
                elif op == "scale" and path == "entry/sample/rig_json" and path in fh:
                    d = _json.loads(fh[path][()])
                    key = ["nominal_wave_speed_m_s", "steady_flow_m3_s", "reservoir_head_m"][i % 3]
                    d[key] = value if np.isfinite(value) else "nan"
                    del fh[path]
                    fh[path] = _json.dumps(d)
            except (TypeError, ValueError, KeyError, OSError):
                pass
    argv = command.split() + [str(case)]
    if command == "fit":
        argv += ["--models", "0", "--window", "0.5", "--no-polish", "--starts", "1"]
    before = {case: case.read_bytes()}
    code, out, err = run_main(argv)
    _check_outcome(argv, code, out, err, before)
    if command == "info --json":
        _json.loads(out)  # every JSON output parses


@ENTRY_BUDGET
@given(scale=st.sampled_from([1.0, 9.79, 1e3, 1e-5, 1e300, -1.0]),
       step=st.sampled_from([1e-3, 1e-300, 1e300, 1e-9, 0.5]),
       extra=st.sampled_from(["", ",7", ",", "\0"]),
       header=st.sampled_from(["time,head", "head,head", "time;head", "t,h,x"]),
       units=st.sampled_from(["m", "kPa", "bar", "Pa"]))
def test_mutated_csvs_through_import(tmp_path_factory, scale, step, extra, header, units):
    d = tmp_path_factory.mktemp("csv")
    csv = d / "r.csv"
    rows = "".join(f"{(i - 20) * step!r},{34.7 * scale + (i % 7) * 0.1!r}{extra}\n" for i in range(200))
    csv.write_text(f"{header}\n{rows}")
    argv = ["import", str(csv), "--rig", "perugia", "--units", units, "-o", str(d / "out.h5")]
    before = {csv: csv.read_bytes()}
    code, out, err = run_main(argv)
    _check_outcome(argv, code, out, err, before)
    if code == 0:  # accepted: it makes sense on the rig (heads its transducer reads, a DAQ's rate)
        from velab.runfiles import read_run

        run = read_run(d / "out.h5")
        assert run.sound and 0.1 <= run.sample_rate_hz <= 1e6
        assert float(np.nanmax(np.abs(run.head_m))) < 100
    else:
        assert not (d / "out.h5").exists()


import numpy as np  # noqa: E402
