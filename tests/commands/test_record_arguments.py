"""`velab record`'s own arguments are checked at the door by velab.bounds, as `velab synth`'s (issue 52).

A value that is not physical (a closure beta of 1e9 1/s, a gamma that shuts the valve before the
trigger, a sampling rate no DAQ takes, a record of billions of samples) is exit 2 with one line
naming the option, before the output folder is made and before any device is connected: against
a bench whose devices cannot be reached, the same command with sound values is a device failure
(exit 5, "connecting"), with a bad value it is exit 2 and nothing is tried.
"""

from __future__ import annotations

import contextlib
import io
import socket
import subprocess
import sys

import pytest

from velab import bounds
from velab.cli import main
from velab.configpath import find_config


def _record(*argv, timeout=120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "velab.cli", "record", *map(str, argv)], capture_output=True,
                          text=True, timeout=timeout)


def test_simulated_record_with_beta_1e9_is_one_line_and_no_run_file(tmp_path):
    out = tmp_path / "runs"
    p = _record("--simulate", "--fast", "--beta", "1e9", "--duration", "2", "--window", "1", "--out-dir", out)
    assert p.returncode == 2, p.stderr
    err = p.stderr
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert "--beta" in err and bounds.BETA_PER_S.describe().split()[0] in err and "1e9" in err, err
    assert p.stdout == "" and not out.exists()  # no folder, no run file


def _free_port() -> int:
    with socket.socket() as s:  # a loopback port nobody listens on
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def unreachable_bench(tmp_path):
    """The LabJack bench with every device on a loopback port nobody serves."""
    port = _free_port()
    text = find_config("benches", "labjack").read_text()
    for old, new in (("port = 15050", f"port = {port}"), ("stream_port = 15051", f"stream_port = {port}"),
                     ("socket://127.0.0.1:15053", f"socket://127.0.0.1:{port}")):
        assert old in text
        text = text.replace(old, new)
    path = tmp_path / "unreachable.toml"
    path.write_text(text)
    return path


def test_bad_values_are_refused_before_anything_connects(unreachable_bench, tmp_path):
    out = tmp_path / "runs"
    base = ["--config", unreachable_bench, "--out-dir", out, "--no-fit", "--duration", "2"]
    p = _record(*base)  # sound values: it tries the bench, which is not there
    assert p.returncode == 5 and "connecting" in p.stderr, p.stderr
    for bad, words in ((["--beta", "1e9"], ["--beta", "1e9"]),
                       (["--gamma", "3"], ["--gamma", "[-100, 0]"]),
                       (["--rate", "1e7"], ["--rate", "Hz"]),
                       (["--rate", "1e6", "--duration", "3600"], ["samples", f"{bounds.MAX_SAMPLES:,}"])):
        p = _record(*base, *bad)
        assert p.returncode == 2, (bad, p.stderr)
        assert p.stderr.count("\n") == 1 and "connecting" not in p.stderr, p.stderr
        assert all(w in p.stderr for w in words), (bad, p.stderr)


def _main(argv) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            code = main([str(a) for a in argv])
        except SystemExit as exc:
            code = exc.code
    return code, err.getvalue()


@pytest.mark.parametrize("args,words", [
    (["--beta", "0.0001"], ["--beta", "[0.001, 10000] 1/s"]),        # bounds.BETA_PER_S, as synth
    (["--beta", "1e9"], ["--beta"]),
    (["--gamma", "5"], ["--gamma", "[-100, 0]"]),                    # bounds.GAMMA: valve half open at the trigger
    (["--gamma", "-1e3"], ["--gamma"]),
    (["--rate", "0.01"], ["--rate", "[0.1, 1e+06] Hz"]),             # bounds.SAMPLE_RATE_HZ
    (["--sample-rate", "2e6"], ["--sample-rate"]),
    (["--duration", "0"], ["--duration", "(0, 3600] s"]),
    (["--duration", "1e5"], ["--duration"]),
    (["--pretrigger", "0"], ["--pretrigger", "[0.05, 600] s"]),
    (["--pretrigger", "1e4"], ["--pretrigger"]),
    (["--ceiling", "0"], ["--ceiling", "(0, 100000] m"]),           # bounds.HEAD_M: no pipe holds 10 kbar
    (["--ceiling", "1e9"], ["--ceiling"]),
    (["--window", "1e5"], ["--window", "(0, 3600] s"]),
    (["--rate", "1e6", "--duration", "100"], ["1.02e+08 samples", "--rate", "--duration"]),  # bounds.MAX_SAMPLES
    (["--beta", "0.001", "--gamma", "-10"], ["half closure 1e+04 s", "--gamma", "--beta"]),  # bounds.HALF_CLOSURE_S
])
def test_each_bound_is_one_line_exit_2(tmp_path, args, words):
    out = tmp_path / "runs"
    code, err = _main(["record", "--simulate", "--out-dir", out, *args])
    assert code == 2, err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    for w in words:
        assert w in err, (w, err)
    assert not out.exists()


def test_the_record_options_take_what_synth_takes():
    """The same bound objects at both doors: what synth calls physical, record does."""
    import argparse

    from velab.cli import build_parser

    commands = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices

    def types(command):
        return {a.dest: a.type for a in commands[command]._actions if a.option_strings}

    rec, syn = types("record"), types("synth")
    for dest in ("beta", "gamma", "rate", "duration"):
        assert (rec[dest].lo, rec[dest].hi, rec[dest].lo_open) == (syn[dest].lo, syn[dest].hi, syn[dest].lo_open), dest
