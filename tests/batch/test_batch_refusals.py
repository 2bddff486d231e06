"""A batch refuses, per run and before fitting it, a run it could not save into (issue 52).

A run still open for writing (a live SWMR RunWriter in another process, as the recorder holds it)
and a damaged run (its structure not a run's: velab.runfiles.soundness) are refused as
``velab fit RUN`` refuses them: not fitted, reported ``refused`` with the reason, the file left as
it was, the batch's exit code the worst run's (docs/cli.md: 5 for the open run, 2 for the damaged
one). With ``--no-save`` both are fitted, as a single run is.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import pytest

from velab.cli import main

FIT = ["--models", "0-1", "--window", "2", "--starts", "1"]

LIVE_WRITER = """
import sys
from velab.runfiles import read_run, RunWriter
r = read_run(sys.argv[1])
w = RunWriter(sys.argv[2], r.rig, sample_rate_hz=r.sample_rate_hz, title="live")
w.append(r.time_s, head=r.head_m)
w.flush()
print("ready", flush=True)
sys.stdin.readline()  # held open for writing until the test closes our stdin
"""


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    p = tmp_path_factory.mktemp("refusals") / "base.h5"
    assert main(["synth", "--material", "A", "--rate", "200", "--duration", "3", "--friction", "linear",
                 "-o", str(p)]) == 0
    return p


@pytest.fixture
def live(base, tmp_path):
    """A run being recorded: its writer (another process) holds it open for writing."""
    path = tmp_path / "live.h5"
    proc = subprocess.Popen([sys.executable, "-c", LIVE_WRITER, str(base), str(path)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        yield path
    finally:
        proc.stdin.close()
        proc.wait(timeout=60)


def _copy(base: Path, path: Path) -> Path:
    shutil.copy(base, path)
    return path


def _damaged(base: Path, path: Path) -> Path:
    shutil.copy(base, path)
    with h5py.File(path, "r+") as fh:
        del fh["entry/manoeuvre"]
    return path


def _digest(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _fits(p: Path) -> list[str]:
    with h5py.File(p, "r") as fh:
        return list(fh["entry"].get("fits", {}))


@pytest.fixture
def fitted(monkeypatch):
    """The paths the fit path fitted (velab.fitting.entry.fit_run, spied on, in this process: --jobs 1)."""
    import velab.fitting.entry as entry

    seen: list[str] = []
    real = entry.fit_run

    def spy(run, *a, **k):
        seen.append(str(run.path))
        return real(run, *a, **k)

    monkeypatch.setattr(entry, "fit_run", spy)
    return seen


def _batch(capsys, *argv) -> tuple[int, dict | str, str]:
    capsys.readouterr()
    code = main(["fit", *map(str, argv), *FIT])
    out = capsys.readouterr()
    return code, (json.loads(out.out) if "--json" in argv else out.out), out.err


def test_open_and_damaged_runs_refused_before_fitting(base, live, tmp_path, capsys, fitted):
    good = _copy(base, tmp_path / "good.h5")
    damaged = _damaged(base, tmp_path / "damaged.h5")
    before = {p: _digest(p) for p in (live, damaged)}
    code, doc, err = _batch(capsys, good, live, damaged, "--json")
    assert fitted == [str(good)]  # neither refused run was fitted
    by = {Path(r["path"]).name: r for r in doc["runs"]}
    assert by["good.h5"]["status"] == "saved" and _fits(good) == ["auto_w2s"]
    assert by["live.h5"] == {**by["live.h5"], "status": "refused", "reason": "run open", "exit_code": 5}
    assert "still open for writing" in by["live.h5"]["error"] and "velab recover" in by["live.h5"]["error"]
    assert by["damaged.h5"] == {**by["damaged.h5"], "status": "refused", "reason": "damaged run", "exit_code": 2}
    assert "no /entry/manoeuvre" in by["damaged.h5"]["error"]
    assert "models" not in by["live.h5"] and "models" not in by["damaged.h5"]
    assert doc["batch"] == {**doc["batch"], "runs": 3, "fitted": 1, "refused": 2, "failed": 0, "exit_code": 2}
    assert code == 2  # the worst run decides: a bad input (2) over a storage failure (5)
    assert err.splitlines() == [f"velab: REFUSED {live} (run open): {by['live.h5']['error']}",
                                f"velab: REFUSED {damaged} (damaged run): {by['damaged.h5']['error']}"]
    for p, digest in before.items():
        assert _digest(p) == digest  # nothing written into either


def test_a_run_open_for_writing_makes_the_batch_a_storage_failure(base, live, tmp_path, capsys, fitted):
    good = [_copy(base, tmp_path / f"good{i}.h5") for i in range(2)]
    before = _digest(live)
    code, out, err = _batch(capsys, good[0], live, good[1])
    assert code == 5 and sorted(fitted) == sorted(map(str, good))
    rows = {line.split()[0]: line for line in out.splitlines()[1:4]}
    assert rows["live.h5"].split()[1:4] == ["REFUSED", "run", "open"]
    assert rows["good0.h5"].split()[1] == "saved" and rows["good1.h5"].split()[1] == "saved"
    assert "3 runs: 2 fitted, 0 failed, 1 refused" in out
    assert err.count("\n") == 1 and err.startswith(f"velab: REFUSED {live} (run open): ")
    assert _digest(live) == before


def test_no_save_fits_them_and_writes_nothing(base, live, tmp_path, capsys, fitted):
    good = _copy(base, tmp_path / "good.h5")
    damaged = _damaged(base, tmp_path / "damaged.h5")
    before = {p: _digest(p) for p in (good, live, damaged)}
    code, doc, err = _batch(capsys, good, live, damaged, "--json", "--no-save")
    assert code == 0 and sorted(fitted) == sorted(map(str, (good, live, damaged)))
    assert [r["status"] for r in doc["runs"]] == ["fitted"] * 3
    assert doc["batch"] == {**doc["batch"], "fitted": 3, "refused": 0, "failed": 0, "exit_code": 0}
    assert "nothing written into it" in err
    for p, digest in before.items():
        assert _digest(p) == digest


def test_refused_in_worker_processes_too(base, live, tmp_path):
    """--jobs 2: the refusal is made in the pool's process, and travels back as data."""
    good = [_copy(base, tmp_path / f"good{i}.h5") for i in range(2)]
    damaged = _damaged(base, tmp_path / "damaged.h5")
    p = subprocess.run([sys.executable, "-m", "velab.cli", "fit", *map(str, (*good, live, damaged)), *FIT,
                        "--jobs", "2", "--json"], capture_output=True, text=True, timeout=240)
    assert p.returncode == 2, p.stderr
    doc = json.loads(p.stdout)
    assert [(r["status"], r.get("reason")) for r in doc["runs"]] == [
        ("saved", None), ("saved", None), ("refused", "run open"), ("refused", "damaged run")]
    assert _fits(damaged) == [] and "Traceback" not in p.stderr


def test_a_run_opened_for_writing_after_its_fit_is_refused_at_the_save(base, live, tmp_path):
    """The race: a recorder opens the run between its fit and the client's save: refused, exit 5. The fit runs
    on the fit service's in-process backend; the live writer's file takes the run's place as the fit ends."""
    from velab.batch.runner import run_batch
    from velab.cli import build_parser
    from velab.commands.fit import _options, fit_request
    from velab.fitservice import FitService
    from velab.fitservice.future import FitFuture, settle
    from velab.fitservice.thread import ThreadBackend

    class OpenedAfterTheFit(ThreadBackend):
        def submit(self, request, progress=None):
            inner, outer = super().submit(request, progress), FitFuture(request)

            def ended(f):
                os.replace(live, request.source.path)  # the live writer's file now stands where the fitted run was
                outer.where, outer.seconds = f.where, f.seconds
                settle(outer, *((f.result(),) if f.exception() is None else (None, f.exception())))
            inner.add_done_callback(ended)
            return outer

    target = _copy(base, tmp_path / "target.h5")
    opts = _options(build_parser().parse_args(["fit", "x.h5", *FIT]))
    batch = run_batch(fit_request, [str(target)], opts, service=FitService(OpenedAfterTheFit()))
    (o,) = batch.outcomes
    assert o["status"] == "refused" and o["reason"] == "run open" and o["exit_code"] == 5, o
    assert "not written" in o["error"]
    from velab.batch import report

    assert report.exit_code(batch) == 5 and report.counts(batch) == {"fitted": 0, "refused": 1, "failed": 0}
