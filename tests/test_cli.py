"""The velab CLI as one program: global options, logging, exit codes, strict JSON, input bounds,
progress on a terminal, light start-up."""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from velab import __version__
from velab.cli import COMMAND_MODULES, main
from velab.commands.common import Number, float_range, int_range, json_ready, positive_float, write_json
from velab.errors import ExitCode

ROOT = Path(__file__).resolve().parents[1]


def strict_json(text: str):
    def refuse(name):
        raise ValueError(f"not JSON: {name}")

    return json.loads(text, parse_constant=refuse)


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    path = tmp_path_factory.mktemp("run") / "a.h5"
    assert main(["synth", "--rate", "500", "--duration", "3", "-o", str(path)]) == 0
    return path


# ------------------------------------------------------------------ global options


def test_version(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0 and capsys.readouterr().out.strip() == f"velab {__version__}"


def test_no_command_prints_help_and_exits_2(capsys):
    assert main([]) == 2
    assert "synth" in capsys.readouterr().err


def test_help_lists_every_registered_command(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    for module in COMMAND_MODULES:
        try:
            __import__(module)
        except ModuleNotFoundError:
            continue  # registered on another branch
        name = {"import_csv": "import"}.get(module.rsplit(".", 1)[1], module.rsplit(".", 1)[1])
        assert name in out
    assert "exit codes" in out.lower()


def test_global_options_before_or_after_the_command(small_run, tmp_path, capsys):
    log = tmp_path / "velab.log"
    assert main(["-v", "info", str(small_run), "--log-file", str(log)]) == 0
    assert "velab" in log.read_text()  # debug level in the file: the invocation
    capsys.readouterr()
    assert main(["info", "--quiet", str(small_run)]) == 0
    assert capsys.readouterr().err == ""


def test_log_file_in_a_missing_directory_is_one_line(small_run, tmp_path, capsys):
    assert main(["--log-file", str(tmp_path / "nodir" / "x.log"), "info", str(small_run)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--log-file" in err


def test_verbose_logs_progress_when_not_a_tty(tmp_path, capsys):
    out = tmp_path / "b.h5"
    assert main(["synth", "--rate", "500", "--duration", "2", "-o", str(out)]) == 0
    assert capsys.readouterr().err == ""  # not a terminal: nothing but errors on stderr
    assert main(["-v", "synth", "--rate", "500", "--duration", "2", "-o", str(out), "--force"]) == 0
    assert "synthesising" in capsys.readouterr().err


# ------------------------------------------------------------------ exit codes


def test_exit_code_table_is_documented_once():
    doc = (ROOT / "docs" / "cli.md").read_text()
    for code in ExitCode:
        assert re.search(rf"^\| {int(code)} \| `{code.name}` \|", doc, re.M), f"{code!r} missing from docs/cli.md"
    assert ExitCode.worst([0, 3, 130]) == ExitCode.INTERRUPTED
    assert ExitCode.worst([4, 5]) == ExitCode.FAILURE and ExitCode.worst([5, 2]) == ExitCode.BAD_INPUT
    assert ExitCode.worst([]) == ExitCode.OK and ExitCode.worst([77]) == ExitCode.FAILURE


# ------------------------------------------------------------------ argument domains


def test_number_types():
    assert positive_float("2.5") == 2.5
    for bad in ("0", "-1", "nan", "inf", "1e999", "x", ""):
        with pytest.raises(argparse.ArgumentTypeError):
            positive_float(bad)
    r = float_range(0, 10, hi_open=True, units="s")
    assert r("0") == 0 and r("9.5") == 9.5
    with pytest.raises(argparse.ArgumentTypeError, match=r"\[0, 10\) s"):
        r("10")
    i = int_range(1, 64)
    assert i("64") == 64
    for bad in ("0", "65", "1.5", "9" * 5000):
        with pytest.raises(argparse.ArgumentTypeError):
            i(bad)
    assert isinstance(i, Number) and i.contains(3) and not i.contains(math.nan)


@pytest.mark.parametrize("argv,expect", [
    (["synth", "--rate", "1e9"], "--rate"),                 # bounded before anything is allocated
    (["synth", "--rate", "1e6", "--duration", "3600"], "samples"),
    (["synth", "--rate", "10"], "cannot resolve the manoeuvre"),
    (["synth", "--rate", "30", "--beta", "32"], "use at least"),
    (["synth", "--noise", "inf"], "--noise"),
    (["synth", "--gamma", "nan"], "--gamma"),
    (["synth", "--beta", "1e300"], "--beta"),
    (["synth", "--seed", "-1"], "--seed"),
    (["synth", "--duration", "0"], "--duration"),
])
def test_synth_refuses_nonsense(argv, expect, tmp_path, capsys):
    out = tmp_path / "x.h5"
    try:
        code = main([*argv, "-o", str(out)])
    except SystemExit as exc:
        code = exc.code
    err = capsys.readouterr().err
    assert code == 2 and expect in err and err.count("\n") == 1, err
    assert not out.exists()


def test_fit_plot_into_a_missing_directory_is_one_line(small_run, tmp_path, capsys):
    code = main(["fit", str(small_run), "--plot", str(tmp_path / "nodir" / "fig.png"), "--no-save"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "does not exist" in err and "Traceback" not in err


@pytest.mark.parametrize("models", ["0-1000000000000", "7", "x", "-1-3"])
def test_fit_bad_model_list_is_one_line(models, small_run, capsys):
    assert main(["fit", str(small_run), f"--models={models}", "--no-save"]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_fit_bad_method_and_name(small_run, capsys):
    assert main(["fit", str(small_run), "--method", "magic", "--no-save"]) == 2
    assert "choose from" in capsys.readouterr().err
    before = small_run.read_bytes()
    assert main(["fit", str(small_run), "--name", "a/b"]) == 2  # checked before any fitting
    err = capsys.readouterr().err
    assert "fit name 'a/b' is not allowed" in err and err.count("\n") == 1
    assert small_run.read_bytes() == before


def test_config_of_dev_zero_is_refused(tmp_path, capsys):
    assert main(["synth", "--rig", "/dev/zero", "-o", str(tmp_path / "x.h5")]) == 2
    assert "not a regular file" in capsys.readouterr().err


def test_import_refuses_special_and_huge_files(tmp_path, capsys):
    assert main(["import", "/dev/zero", "--rig", "perugia", "-o", str(tmp_path / "x.h5")]) == 2
    assert "not a regular file" in capsys.readouterr().err


# ------------------------------------------------------------------ JSON


def test_write_json_is_strict(capsys):
    write_json({"a": math.nan, "b": [math.inf, -math.inf, 1.5], "c": np.float64("nan"), "d": np.arange(3),
                "e": np.int64(7), "f": Path("/x"), "g": (1, 2)})
    doc = strict_json(capsys.readouterr().out)
    assert doc == {"a": None, "b": [None, None, 1.5], "c": None, "d": [0, 1, 2], "e": 7, "f": "/x", "g": [1, 2]}
    assert json_ready({1: math.nan}) == {"1": None}


def test_info_json(small_run, capsys):
    assert main(["info", "--json", str(small_run)]) == 0
    doc = strict_json(capsys.readouterr().out)
    assert doc["path"] == str(small_run) and doc["status"] == "synthetic" and doc["n_samples"] == 500 * 4
    assert doc["rig"]["name"] and doc["material"]["name"] == "A" and doc["fits"] == {}
    assert main(["info", "--json", str(small_run), str(small_run)]) == 0
    assert len(strict_json(capsys.readouterr().out)["runs"]) == 2


def test_fit_json_is_strict(small_run, capsys):
    assert main(["fit", str(small_run), "--models", "0-1", "--window", "2.5", "--no-polish", "--json", "--no-save"]) == 0
    doc = strict_json(capsys.readouterr().out)
    assert doc["path"] == str(small_run) and {m["name"] for m in doc["models"]} == {"EL", "S1"}


# ------------------------------------------------------------------ terminal, start-up


def test_fit_in_a_terminal_shows_progress_on_stderr(small_run):
    """`velab fit` with a pseudo-terminal on stdout/stderr (the path that crashed on `rich`)."""
    import pty

    master, slave = pty.openpty()
    try:
        proc = subprocess.Popen([sys.executable, "-m", "velab.cli", "fit", str(small_run), "--models", "0-1",
                                 "--window", "2.5", "--no-polish", "--no-save"], stdin=slave, stdout=slave, stderr=slave,
                                close_fds=True)
        os.close(slave)
        chunks = []
        while True:
            try:
                data = os.read(master, 4096)
            except OSError:  # EIO: the child closed the terminal
                break
            if not data:
                break
            chunks.append(data)
        assert proc.wait(timeout=120) == 0
    finally:
        os.close(master)
    text = b"".join(chunks).decode(errors="replace")
    assert "Traceback" not in text and "best" in text.lower()
    assert "\x1b[2K" in text and "models" in text  # the live progress line, redrawn and erased


def test_help_imports_no_heavy_package():
    out = subprocess.run([sys.executable, "-X", "importtime", "-m", "velab.cli", "--help"], capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0
    imported = {line.split("|")[-1].strip().split(".")[0] for line in out.stderr.splitlines() if "|" in line}
    heavy = imported & {"numpy", "scipy", "h5py", "matplotlib", "PySide6", "pyqtgraph", "pymodbus", "serial"}
    assert not heavy, f"velab --help imports {heavy}: lazy-import them inside the command"
