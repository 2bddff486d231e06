"""velab.runfiles.probe: the child that walks a file's HDF5 structure before this process reads it is kept
for the next file, replaced after a damaged file, not shared with a forked process, and bounded by its
deadline (VELAB_PROBE_TIMEOUT_S); started ahead (start_walker, velab fit) without being waited for."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time

import pytest

from velab.cli import main
from velab.errors import DataError
from velab.runfiles import probe


@pytest.fixture(scope="module")
def sound(tmp_path_factory):
    p = tmp_path_factory.mktemp("probe") / "a.h5"
    assert main(["synth", "--material", "A", "--rate", "200", "--duration", "2", "--friction", "linear",
                 "-o", str(p), "-q"]) == 0
    return p


def _copy(src, d, name):
    p = d / name
    shutil.copy(src, p)
    return p


def _forget():
    with probe._lock:
        probe._known.clear()


def test_one_child_walks_many_files(sound, tmp_path):
    _forget()
    probe.ensure_walkable(_copy(sound, tmp_path, "1.h5"))
    first = probe._walker
    assert first is not None and first.proc.poll() is None
    for i in range(2, 6):
        probe.ensure_walkable(_copy(sound, tmp_path, f"{i}.h5"))
    assert probe._walker is first  # the same process: one start-up for the batch


def test_a_damaged_file_is_named_and_its_child_replaced(sound, tmp_path, monkeypatch):
    """Zeroed object headers make HDF5 loop: the walk ends at its deadline, the file is named."""
    _forget()
    monkeypatch.setenv("VELAB_PROBE_TIMEOUT_S", "1")
    probe.ensure_walkable(_copy(sound, tmp_path, "ok.h5"))
    before = probe._walker
    bad = tmp_path / "bad.h5"
    data = sound.read_bytes()
    bad.write_bytes(data[:4096] + bytes(2048) + data[6144:])  # object headers zeroed
    with pytest.raises(DataError, match="bad.h5: damaged HDF5 file"):
        probe.ensure_walkable(bad)
    assert before.proc.poll() is not None  # not reused after a failure
    probe.ensure_walkable(_copy(sound, tmp_path, "ok2.h5"))  # a fresh one serves the next file
    assert probe._walker is not before and probe._walker.proc.poll() is None


def test_a_forked_process_starts_its_own_child(sound, tmp_path):
    _forget()
    probe.ensure_walkable(_copy(sound, tmp_path, "p.h5"))
    parent_child = probe._walker.proc.pid
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the forked side
        code = 1
        try:
            probe.ensure_walkable(_copy(sound, tmp_path, "c.h5"))
            code = 0 if probe._walker.proc.pid != parent_child else 2
        finally:
            os.write(w, bytes([code]))
            os._exit(0)
    os.close(w)
    answer = os.read(r, 1)
    os.waitpid(pid, 0)
    assert answer == b"\x00"
    assert probe._walker.proc.pid == parent_child and probe._walker.proc.poll() is None  # ours untouched
    probe.ensure_walkable(_copy(sound, tmp_path, "p2.h5"))


@pytest.mark.parametrize("value", ["0", "-1", "soon", "inf"])
def test_a_bad_deadline_is_one_line_naming_the_variable(sound, tmp_path, monkeypatch, value):
    _forget()
    monkeypatch.setenv("VELAB_PROBE_TIMEOUT_S", value)
    with pytest.raises(DataError, match="^VELAB_PROBE_TIMEOUT_S: expected a number of seconds > 0") as e:
        probe.ensure_walkable(_copy(sound, tmp_path, "x.h5"))
    assert "\n" not in str(e.value)


WALK_DEADLINE_S = 4.0  # a small file's walk: ~40 ms of CPU; 1 s was missed at load 16 on a 2-core host
SLOW_START_S = WALK_DEADLINE_S + 1.0


def test_the_deadline_is_the_walks_not_the_start_up(sound, tmp_path, monkeypatch):
    """A deadline shorter than a fresh child's start-up still passes a sound file: start-up is apart. The
    child's start-up is made longer than the deadline (a sitecustomize that sleeps, as a cold disk or a loaded
    host would); the deadline is ample for the walk of a small file on a loaded host."""
    _forget()
    if probe._walker is not None:
        probe._walker.close()
        probe._walker = None
    slow = tmp_path / "slow_start"
    slow.mkdir()
    (slow / "sitecustomize.py").write_text(f"import time\ntime.sleep({SLOW_START_S!r})\n")
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(slow), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))
    monkeypatch.setenv("VELAB_PROBE_TIMEOUT_S", str(WALK_DEADLINE_S))
    t0 = time.monotonic()
    probe.ensure_walkable(_copy(sound, tmp_path, "quick.h5"))
    assert time.monotonic() - t0 >= SLOW_START_S  # (the start-up did take longer than the deadline)
    probe._walker.close()  # (not kept for the other tests: it starts slowly)
    probe._walker = None


def _no_walker():
    if probe._walker is not None:
        probe._walker.close()
        probe._walker = None


def test_start_walker_starts_the_child_without_waiting_and_the_walk_uses_it(sound, tmp_path):
    """velab fit starts the child as soon as it knows its files (before its own imports): the call returns at once,
    the child's start-up runs beside this process, and the first walk is served by that child."""
    _forget()
    _no_walker()
    p = _copy(sound, tmp_path, "ahead.h5")
    probe.start_walker([str(p)])
    started = probe._walker
    assert started is not None and not started.ready and started.owner == os.getpid()
    probe.start_walker([str(p)])  # a second call keeps it
    assert probe._walker is started
    probe.ensure_walkable(p)
    assert probe._walker is started and started.ready and started.proc.poll() is None


def test_start_walker_starts_nothing_for_files_it_would_not_walk(sound, tmp_path, monkeypatch):
    _forget()
    _no_walker()
    probe.start_walker([str(tmp_path / "missing.h5")])  # the read will say what is wrong: no child for it
    known = _copy(sound, tmp_path, "known.h5")
    probe.trust(known)  # written by this process
    probe.start_walker([known])
    assert probe._walker is None
    monkeypatch.setenv("VELAB_PROBE_CHILD", "1")  # the child itself: no grandchildren
    probe.start_walker([_copy(sound, tmp_path, "other.h5")])
    assert probe._walker is None


def test_a_child_started_ahead_and_never_used_does_not_hold_up_the_exit(sound, tmp_path):
    """A command that fails before reading its file (a bad option) exits at once: the child started ahead is
    killed at exit, not waited for (its start-up made longer than the wait would be, as on a loaded host)."""
    slow = tmp_path / "slow_start"
    slow.mkdir()
    (slow / "sitecustomize.py").write_text("import time\ntime.sleep(30)\n")
    code = ("import os, sys, time\n"
            f"os.environ['PYTHONPATH'] = {str(slow)!r} + os.pathsep + os.environ.get('PYTHONPATH', '')\n"
            "from velab.runfiles import probe\n"
            f"probe.start_walker([{str(_copy(sound, tmp_path, 'never.h5'))!r}])\n"
            "assert probe._walker is not None and not probe._walker.ready\n"
            "print(probe._walker.proc.pid, flush=True)\n")
    t0 = time.monotonic()
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    assert time.monotonic() - t0 < 20  # not the child's 30 s start-up
    pid = int(p.stdout.split()[0])
    with pytest.raises(ProcessLookupError):  # killed and reaped by its parent before it ended
        os.kill(pid, 0)
