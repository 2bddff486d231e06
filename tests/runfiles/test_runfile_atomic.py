"""Nothing velab does can damage a recorded run (issue 11 item 4).

* SIGKILL of a real `velab fit` at every stage of its save, and at random instants,
  and of the recorder's save path (the same `save_fit`, in a subprocess): the run
  stays readable and everything outside /entry/fits is bit-identical.
* `--name` can only name a fit.
* Concurrent saves into one run are serialised (the lock), none is lost.
* Runs left flagged "open for write" (killed SWMR writer; killed old-style in-place
  save) are readable, refuse saves, and `velab recover` writes a clean copy with its
  end_time, never touching the original.
"""

from __future__ import annotations

import os
import random
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
from velab.runfiles import read_run, save_fit
from velab.runfiles.atomic import STAGE_ENV, STAGES
from velab.runfiles.superblock import read_superblock

FIT = ["--models", "0", "--window", "1", "--no-polish", "--starts", "1"]


def recorded_state(path) -> dict:
    """Every object outside /entry/fits: dtype, shape, raw bytes of the values, and every attribute."""
    out = {}
    with h5py.File(path, "r", locking=False) if not read_superblock(path).open_for_write else \
            h5py.File(path, "r", swmr=True, locking=False) as fh:
        out["/@"] = {k: repr(v) for k, v in fh.attrs.items()}

        def visit(name, obj):
            if name == "entry/fits" or name.startswith("entry/fits/"):
                return
            attrs = {k: repr(v) for k, v in obj.attrs.items()}
            if isinstance(obj, h5py.Dataset):
                v = obj[()]
                raw = v.tobytes() if isinstance(v, np.ndarray) and v.dtype.kind != "O" else repr(v)
                out[name] = (str(obj.dtype), obj.shape, raw, attrs)
            else:
                out[name] = ("group", attrs)

        fh.visititems(visit)
    return out


@pytest.fixture(scope="module")
def big_run(tmp_path_factory):
    """A synthetic run of 2.8 MB: the copy takes more than one block, so `copying` is an instant too."""
    p = tmp_path_factory.mktemp("atomic") / "run.h5"
    assert main(["synth", "--rate", "10000", "--duration", "10", "--pretrigger", "0.5", "-o", str(p)]) == 0
    return p


def _velab(*args, env_extra=None, **kw):
    env = dict(os.environ, **(env_extra or {}))
    return subprocess.Popen([sys.executable, "-m", "velab.cli", *args], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kw)


def _kill_at_stage(proc, stage: str) -> None:
    deadline = time.monotonic() + 120
    line = ""
    while time.monotonic() < deadline:
        line = proc.stderr.readline()
        if not line or line.strip() == f"velab-stage {stage}":
            break
    assert line.strip() == f"velab-stage {stage}", f"never reached {stage}: {line!r} {proc.stderr.read()}"
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)


def _check_intact(path, state, expect_fit: str | None, absent: str | None):
    run = read_run(path)  # readable: one of the two complete versions is under the name
    assert not run.open_for_write
    assert recorded_state(path) == state  # the recorded data and every attribute: bit-identical
    if expect_fit:
        assert expect_fit in run.fit_names
    if absent:
        assert absent not in run.fit_names


# ten `velab fit` processes one after the other, each paying the fit path's imports (~4 s of CPU on a 2-core Intel
# host) before its save: the suite's 300 s ran out under a load of 12 (two other suites beside it), not a hang
@pytest.mark.timeout(600)
def test_sigkill_of_velab_fit_at_every_stage_of_the_save(big_run, tmp_path):
    path = tmp_path / "run.h5"
    shutil.copy(big_run, path)
    state = recorded_state(path)
    for i, stage in enumerate(STAGES):
        name = f"k{i}"
        proc = _velab("fit", str(path), *FIT, "--name", name, env_extra={STAGE_ENV: stage})
        _kill_at_stage(proc, stage)
        assert proc.returncode == -signal.SIGKILL
        # after the rename the new file (with the fit) is the run; before it, the old one
        replaced = STAGES.index(stage) >= STAGES.index("replaced")
        _check_intact(path, state, name if replaced else None, None if replaced else name)
    # a later save removes what the killed ones left (hidden temporary copies) and works
    assert main(["fit", str(path), *FIT, "--name", "after"]) == 0
    assert not list(tmp_path.glob(".run.h5.*.part"))
    _check_intact(path, state, "after", None)
    assert main(["info", str(path)]) == 0


def test_sigkill_of_velab_fit_at_random_instants(big_run, tmp_path):
    """Kills at random times over a whole `velab fit` (start-up, fit, save)."""
    path = tmp_path / "run.h5"
    shutil.copy(big_run, path)
    state = recorded_state(path)
    rng = random.Random(11)
    for i in range(4):
        proc = _velab("fit", str(path), *FIT, "--name", f"r{i}")
        time.sleep(rng.uniform(0.2, 2.5))
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
        _check_intact(path, state, None, None)


RECORDER_SAVE = textwrap.dedent(
    """
    import sys
    from velab.runfiles.fits import save_fit      # what the recorder calls for its online fit
    from velab.runfiles import read_fit_dict, open_run_file
    with open_run_file(sys.argv[1]) as fh:
        doc = read_fit_dict(fh["entry/fits/seed"])
    save_fit(sys.argv[1], doc, "online")
    """
)


def test_sigkill_of_the_recorders_save_path(big_run, tmp_path):
    path = tmp_path / "run.h5"
    shutil.copy(big_run, path)
    assert main(["fit", str(path), *FIT, "--name", "seed"]) == 0
    state = recorded_state(path)
    for stage in STAGES:
        env = dict(os.environ, **{STAGE_ENV: stage})
        proc = subprocess.Popen([sys.executable, "-c", RECORDER_SAVE, str(path)], env=env, stderr=subprocess.PIPE,
                                text=True)
        _kill_at_stage(proc, stage)
        replaced = STAGES.index(stage) >= STAGES.index("replaced")
        _check_intact(path, state, "online" if replaced else None, None if replaced else "online")
        if replaced:  # start again from a run without the online fit
            shutil.copy(big_run, path)
            assert main(["fit", str(path), *FIT, "--name", "seed"]) == 0
            state = recorded_state(path)


def test_concurrent_saves_are_serialised(big_run, tmp_path):
    """A holds the lock (paused 2 s after copying); B must wait, then save on top of A's result."""
    path = tmp_path / "run.h5"
    shutil.copy(big_run, path)
    a = _velab("fit", str(path), *FIT, "--name", "c1", env_extra={STAGE_ENV: "copied:2"})
    line = a.stderr.readline()
    assert line.strip() == "velab-stage copied"
    b = _velab("fit", str(path), *FIT, "--name", "c2")
    assert a.wait(timeout=120) == 0 and b.wait(timeout=120) == 0
    assert {"c1", "c2"} <= set(read_run(path).fit_names)


@pytest.mark.parametrize("name", ["/entry/data", "/entry", "/entry/sample", "/entry/manoeuvre/trigger_time",
                                  "/entry/fits", "..", ".", "/", "", "a/b", "-x", "x" * 65, "é"])
def test_name_can_only_name_a_fit(big_run, tmp_path, capsys, name):
    path = tmp_path / "run.h5"
    shutil.copy(big_run, path)
    before = path.read_bytes()
    assert main(["fit", str(path), *FIT, f"--name={name}"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "fit name" in err and "Traceback" not in err
    assert path.read_bytes() == before


KILLED_SWMR = textwrap.dedent(
    """
    import os, signal, sys
    from velab.runfiles import RunWriter, read_run, Channel, HEAD
    r = read_run(sys.argv[1])
    w = RunWriter(sys.argv[2], r.rig, sample_rate_hz=r.sample_rate_hz, title="killed mid-run",
                  channels=(HEAD, Channel("host_time", "s", group="instrument/adc")))
    w.append(r.time_s, head=r.head_m, host_time=1.7e9 + r.time_s)
    w.event(0.0, "note", "é" * 700)   # longer than one fixed-size row: continues on the next
    w.flush()
    os.kill(os.getpid(), signal.SIGKILL)
    """
)

KILLED_INPLACE = textwrap.dedent(
    """
    import os, signal, sys, h5py
    f = h5py.File(sys.argv[1], "r+")          # an old velab saved fits in place like this
    g = f["entry/fits"].create_group("half")
    g.attrs["method"] = "auto"
    f.flush()
    os.kill(os.getpid(), signal.SIGKILL)
    """
)


def test_killed_swmr_writer_read_refused_for_saves_and_recovered(big_run, tmp_path, capsys):
    killed = tmp_path / "killed.h5"
    proc = subprocess.run([sys.executable, "-c", KILLED_SWMR, str(big_run), str(killed)], timeout=60)
    assert proc.returncode == -signal.SIGKILL
    sb = read_superblock(killed)
    assert sb.open_for_write and sb.swmr_write
    before = killed.read_bytes()
    r = read_run(killed)
    assert r.incomplete and r.open_for_write and not r.end_time
    assert r.events == [(0.0, "note", "é" * 700)]  # not cut: the continuation row is joined back
    assert main(["fit", str(killed), *FIT]) == 5  # refused before the fit: one line naming the remedy
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "still open for writing" in err and "velab recover" in err
    with pytest.raises(Exception, match="still open for writing"):
        save_fit(killed, {"method": "x", "window": 1.0, "models": []}, "x")
    assert main(["recover", str(killed)]) == 0
    assert killed.read_bytes() == before  # the original is never touched
    copy = tmp_path / "killed.recovered.h5"
    assert not read_superblock(copy).open_for_write  # flags cleared, as h5clear -s does
    c = read_run(copy)
    assert c.end_time.startswith(time.strftime("%Y", time.gmtime(1.7e9 + r.time_s[-1])))  # last sample's host clock
    assert "recovered copy of killed.h5" in c.status_reason and c.incomplete
    np.testing.assert_array_equal(c.head_m, r.head_m)
    assert main(["fit", str(copy), *FIT]) == 0 and "saved as /entry/fits/" in capsys.readouterr().out


def test_killed_in_place_save_is_read_and_recovered(big_run, tmp_path, capsys):
    flagged = tmp_path / "flagged.h5"
    shutil.copy(big_run, flagged)
    state = recorded_state(big_run)
    proc = subprocess.run([sys.executable, "-c", KILLED_INPLACE, str(flagged)], timeout=60)
    assert proc.returncode == -signal.SIGKILL
    sb = read_superblock(flagged)
    assert sb.open_for_write and not sb.swmr_write  # HDF5 alone now refuses an ordinary open
    with pytest.raises(OSError):
        h5py.File(flagged, "r")
    before = flagged.read_bytes()
    assert main(["info", str(flagged)]) == 0
    assert "flagged open for writing" in capsys.readouterr().out
    r = read_run(flagged)
    assert r.status == "synthetic" and r.open_for_write
    assert main(["recover", str(flagged)]) == 0
    assert flagged.read_bytes() == before
    copy = tmp_path / "flagged.recovered.h5"
    assert recorded_state(copy) == state  # the recorded data came through bit-identical
    assert main(["fit", str(copy), *FIT]) == 0


def test_recover_refuses_a_closed_run(big_run, capsys):
    assert main(["recover", str(big_run)]) == 2
    assert "nothing to recover" in capsys.readouterr().err
