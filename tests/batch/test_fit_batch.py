"""`velab fit` over many runs (velab.batch): local processes and a real Dask LocalCluster.

Everything Dask runs in subprocesses: the cluster (a real ``distributed.LocalCluster``, two
worker processes, loopback, ephemeral ports) and the ``velab fit --scheduler`` client, as a
lab runs them; so this test process never holds Dask's threads when other tests fork.
The runs are short (3 s at 200 Hz, EL and S1, one start): a fit takes under 0.1 s; the
reader's probe of each file in a child process (velab.runfiles.probe, ~0.3 s) costs more.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import h5py
import pytest

from velab.batch.address import parse_scheduler_address
from velab.cli import main
from velab.runfiles.fits import read_fit_dict

FIT = ["--models", "0-1", "--window", "2", "--starts", "1"]
FIT_NAME = "auto_w2s"
SOURCES = [("A", 1), ("A", 2), ("A", 3), ("B", 1), ("B", 2)]  # five distinct records
# keys that measure the fit's own run time, not its result
TIMING_KEYS = {"date", "duration_s"}

CLUSTER_SCRIPT = r"""
import sys
from distributed import LocalCluster
cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                       scheduler_port=0, dashboard_address=None)
print(cluster.scheduler_address, flush=True)
sys.stdin.read()  # until the test closes our stdin
cluster.close()
"""


def _need_dask():
    pytest.importorskip("distributed", reason="the velab[cluster] extra (dask, distributed) is not installed")


@pytest.fixture(scope="module")
def sources(tmp_path_factory):
    d = tmp_path_factory.mktemp("batch-src")
    out = []
    for material, seed in SOURCES:
        p = d / f"{material}{seed}.h5"
        assert main(["synth", "--material", material, "--seed", str(seed), "--rate", "200", "--duration", "3",
                     "--friction", "linear", "-o", str(p)]) == 0
        out.append(p)
    return out


def _archive(sources, d: Path, n: int = 50) -> list[Path]:
    d.mkdir()
    paths = []
    for i in range(n):
        p = d / f"run{i:02d}.h5"
        shutil.copy(sources[i % len(sources)], p)
        paths.append(p)
    return paths


def _digest(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


# Dask's housekeeping timers, slowed in the test cluster's processes (scheduler, nannies, workers; not the
# client): the event loop's tick monitor (20 ms), the workers' stack profiler (10 ms), the memory, system and
# work-stealing monitors (0.1-0.5 s). At their defaults the idle cluster cost 0.17 CPU-s per second of wall
# time, and the module's cluster lives for its tests (ten minutes of wall in a loaded suite: ~100 s of CPU);
# at these, 0.02. None of them decides where a task runs, when a lost scheduler or worker is noticed
# (heartbeats and comm timeouts keep their defaults) or what a fit computes.
QUIET_DASK = {
    "DASK_DISTRIBUTED__ADMIN__TICK__INTERVAL": "1s",
    "DASK_DISTRIBUTED__ADMIN__SYSTEM_MONITOR__INTERVAL": "5s",
    "DASK_DISTRIBUTED__WORKER__PROFILE__INTERVAL": "1s",
    "DASK_DISTRIBUTED__WORKER__PROFILE__CYCLE": "10s",
    "DASK_DISTRIBUTED__WORKER__MEMORY__MONITOR_INTERVAL": "5s",
    "DASK_DISTRIBUTED__SCHEDULER__WORK_STEALING_INTERVAL": "1s",
}


def _start_cluster():
    proc = subprocess.Popen([sys.executable, "-c", CLUSTER_SCRIPT], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True, start_new_session=True,
                            env=os.environ | QUIET_DASK)
    address = proc.stdout.readline().strip()
    assert address.startswith("tcp://127.0.0.1:"), address
    return proc, address


def _stop_cluster(proc) -> None:
    try:
        proc.stdin.close()
        proc.wait(timeout=60)
    except (subprocess.TimeoutExpired, BrokenPipeError):
        pass
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)  # its worker processes too (their own session)
        except ProcessLookupError:
            pass
        proc.wait()


@pytest.fixture(scope="module")
def cluster():
    _need_dask()
    proc, address = _start_cluster()
    try:
        yield address
    finally:
        _stop_cluster(proc)


def _velab(*args, timeout=240):
    """`velab ARGS` in a fresh interpreter (the client's Dask threads stay out of this process)."""
    return subprocess.run([sys.executable, "-m", "velab.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout)


def _close(a, b, where=""):
    """Two fit documents equal: strings and ints exactly, floats to 1e-9 relative."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and set(a) - TIMING_KEYS == set(b) - TIMING_KEYS, where
        for k in set(a) - TIMING_KEYS:
            _close(a[k], b[k], f"{where}/{k}")
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _close(x, y, f"{where}[{i}]")
    elif _nan(a) or _nan(b):  # JSON writes NaN as null
        assert _nan(a) and _nan(b), where
    elif isinstance(a, float) or isinstance(b, float):
        assert b == pytest.approx(a, rel=1e-9, abs=1e-300), where
    else:
        assert a == b, where


def _nan(v) -> bool:
    return v is None or (isinstance(v, float) and math.isnan(v))


def _stored(p: Path) -> dict:
    with h5py.File(p, "r") as fh:
        return read_fit_dict(fh["entry/fits"][FIT_NAME])


# ------------------------------------------------------------------- the acceptance test


@pytest.mark.timeout(900)  # 100 fits, each run probed in a child process first (velab.runfiles.probe)
def test_fifty_runs_on_a_local_cluster_give_the_local_fits(sources, tmp_path, cluster):
    local = _archive(sources, tmp_path / "local")
    remote = _archive(sources, tmp_path / "cluster")
    heads = {p.name: _head(p) for p in local}
    # the local batch, in this process's pool of two
    code = main(["fit", *map(str, local), *FIT, "--jobs", "2", "--json", "-q"])
    assert code == 0
    # the same batch on the cluster, from a client in its own process
    p = _velab("fit", *remote, *FIT, "--scheduler", cluster, "--json")
    assert p.returncode == 0, p.stderr
    assert p.stderr == ""  # no progress off a terminal, no Dask log records
    doc = json.loads(p.stdout)
    assert doc["batch"] == {**doc["batch"], "runs": 50, "fitted": 50, "failed": 0, "exit_code": 0,
                            "scheduler": cluster}
    runs = {Path(r["path"]).name: r for r in doc["runs"]}
    assert [Path(r["path"]) for r in doc["runs"]] == remote  # in the order given
    # both worker processes fitted runs, and neither is the client
    workers = {r["worker"] for r in doc["runs"]}
    assert len(workers) == 2, workers
    # each stored fit read once (the files do not change from here on; a read is ~50 ms of h5py calls, and the
    # checks below looked at each remote fit three times)
    stored = {p: _stored(p) for p in local + remote}
    for a, b in zip(local, remote):
        assert runs[b.name]["status"] == "saved" and runs[b.name]["fit_name"] == FIT_NAME
        fa, fb = stored[a], stored[b]
        _close(fa, fb, a.name)  # the same fit, stored the same way
        common = set(runs[b.name]) & set(fb)
        assert {"models", "best", "n", "settings"} <= common
        _close({k: runs[b.name][k] for k in common}, {k: fb[k] for k in common}, f"json {b.name}")
        assert _head(b) == heads[a.name]  # the recorded data untouched
    # the five different records gave five different fits, each where it belongs
    best_speed = {round(stored[p]["models"][1]["wave_speed"], 6) for p in remote}
    assert len(best_speed) == len(SOURCES)
    for i, p in enumerate(remote):
        _close(stored[p], stored[remote[i % len(SOURCES)]], p.name)
    assert not [f for f in os.listdir(tmp_path / "cluster") if f.startswith(".")]  # no temporary or lock file


def _head(p: Path) -> str:
    with h5py.File(p, "r") as fh:
        return hashlib.sha256(fh["entry/data/head"][()].tobytes()).hexdigest()


# ------------------------------------------------------------------- failures


def _bad_files(sources, d: Path) -> dict[str, Path]:
    d.mkdir(exist_ok=True)
    files = {}
    for i in range(3):
        files[f"good{i}"] = d / f"good{i}.h5"
        shutil.copy(sources[i], files[f"good{i}"])
    data = sources[0].read_bytes()
    files["truncated"] = d / "truncated.h5"
    files["truncated"].write_bytes(data[: len(data) // 2])
    files["text"] = d / "text.h5"
    files["text"].write_text("not an hdf5 file\n")
    other = d / "other.h5"
    with h5py.File(other, "w") as fh:
        fh["x"] = [1, 2, 3]
    files["other"] = other
    return files


def _check_failures(doc: dict, err: str, files: dict, before: dict) -> None:
    by = {Path(r["path"]).name: r for r in doc["runs"]}
    assert [Path(r["path"]).name for r in doc["runs"]] == [p.name for p in files.values()] + ["missing.h5"]
    for key, p in files.items():
        r = by[p.name]
        if key.startswith("good"):
            assert r["status"] == "saved" and r["best"] in ("EL", "S1") and FIT_NAME in _fits(p)
        else:
            assert r["status"] == "failed" and r["reason"] == "bad input" and r["exit_code"] == 2, r
            assert _digest(p) == before[key]  # a failed run is left exactly as it was
            assert f"velab: FAILED {p} (bad input): " in err
    assert by["missing.h5"]["reason"] == "bad input"
    assert doc["batch"]["failed"] == 4 and doc["batch"]["fitted"] == 3 and doc["batch"]["exit_code"] == 2
    lines = err.strip().splitlines()
    assert len(lines) == 4 and all(line.startswith("velab: FAILED ") for line in lines), err  # one per failure
    assert "Traceback" not in err


def _fits(p: Path) -> list[str]:
    with h5py.File(p, "r") as fh:
        return list(fh["entry"].get("fits", {}))


@pytest.mark.parametrize("jobs", [1, 2])
def test_local_batch_lists_failures_and_goes_on(sources, tmp_path, capsys, jobs):
    files = _bad_files(sources, tmp_path)
    before = {k: _digest(p) for k, p in files.items()}
    capsys.readouterr()
    code = main(["fit", *map(str, files.values()), str(tmp_path / "missing.h5"), *FIT, "--jobs", str(jobs), "--json"])
    out = capsys.readouterr()
    assert code == 2
    _check_failures(json.loads(out.out), out.err, files, before)


def test_cluster_batch_lists_failures_and_goes_on(sources, tmp_path, cluster):
    files = _bad_files(sources, tmp_path)
    before = {k: _digest(p) for k, p in files.items()}
    p = _velab("fit", *files.values(), tmp_path / "missing.h5", *FIT, "--scheduler", cluster, "--json")
    assert p.returncode == 2
    _check_failures(json.loads(p.stdout), p.stderr, files, before)
    # the table names each run's status
    p = _velab("fit", files["good0"], files["text"], *FIT, "--scheduler", cluster, "--no-save")
    assert p.returncode == 2
    rows = {line.split()[0]: line for line in p.stdout.splitlines()[1:3]}
    assert rows["good0.h5"].split()[1] == "fitted" and "FAILED bad input" in rows["text.h5"]
    assert "2 runs: 1 fitted, 1 failed" in p.stdout and f"(dask {cluster})" in p.stdout


def test_table_and_progress(sources, tmp_path, capsys):
    files = _archive(sources, tmp_path / "t", n=3)
    capsys.readouterr()
    assert main(["fit", *map(str, files), *FIT, "--no-save"]) == 0
    out = capsys.readouterr()
    lines = out.out.splitlines()
    assert lines[0].split()[:4] == ["run", "status", "best", "a"]
    for line, p in zip(lines[1:4], files):
        cols = line.split()
        assert cols[0] == p.name and cols[1] == "fitted" and cols[2] in ("EL", "S1") and 300 < float(cols[3]) < 400
        # F / the record's noise, and the fit's warning codes ("-": none)
        assert 0.5 < float(cols[5]) < 3 and cols[-1] in ("-", "bound", "misfit", "bound,misfit"), line
    assert lines[0].split()[-1] == "warnings"
    assert lines[4].startswith("3 runs: 3 fitted, 0 failed")
    assert out.err == ""  # progress only on a terminal, or with -v
    assert all(_fits(p) == [] for p in files)  # --no-save
    # -v off a terminal: the progress as log lines, with a bar
    assert main(["-v", "fit", *map(str, files[:2]), *FIT, "--no-save"]) == 0
    err = capsys.readouterr().err
    assert "velab fit [##########..........] 1/2 runs" in err and "2/2 runs" in err


# ------------------------------------------------------------------- the scheduler address and the extra


def test_scheduler_address_is_checked_before_anything(sources, tmp_path, capsys):
    assert parse_scheduler_address("tcp://10.0.0.5:8786") == "tcp://10.0.0.5:8786"
    assert parse_scheduler_address("TCP://node7.lab:9000") == "tcp://node7.lab:9000"
    assert parse_scheduler_address("tls://[::1]") == "tls://[::1]:8786"
    run = tmp_path / "a.h5"
    shutil.copy(sources[0], run)
    before = _digest(run)
    for bad, why in (("udp://x:1", "protocol"), ("tcp://x:0", "port"), ("tcp://x:70000", "port"),
                     ("tcp://h:1/path", "HOST:PORT"), ("tcp://u@h:1", "HOST:PORT"), ("tcp://::1:8786", "brackets"),
                     ("tcp://:8786", "no host"), ("tcp://bad_host!:1", "host name"), ("", "empty"),
                     ("perugia", "no protocol"), ("10.0.0.5:8786", "no protocol")):
        capsys.readouterr()
        with pytest.raises(SystemExit) as e:
            main(["fit", str(run), "--scheduler", bad])
        err = capsys.readouterr().err.strip()
        assert e.value.code == 2 and "--scheduler" in err and why in err and "\n" not in err, (bad, err)
    assert _digest(run) == before


def test_missing_extra_is_one_line_naming_it(sources, tmp_path):
    run = tmp_path / "a.h5"
    shutil.copy(sources[0], run)
    before = _digest(run)
    # an interpreter where dask and distributed cannot be imported
    code = ("import sys; sys.modules['dask'] = None; sys.modules['distributed'] = None\n"
            "from velab.cli import main; sys.exit(main(sys.argv[1:]))")
    p = subprocess.run([sys.executable, "-c", code, "fit", str(run), *FIT, "--scheduler", "tcp://127.0.0.1:9"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2
    err = p.stderr.strip()
    assert err.startswith("velab: --scheduler needs dask and distributed") and "velab[cluster]" in err
    assert "\n" not in err and p.stdout == ""
    assert _digest(run) == before
    # `velab fit --help` and a local batch never import them
    p = subprocess.run([sys.executable, "-c", code, "fit", str(run), str(run), *FIT, "--no-save", "-q"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr


def test_unreachable_scheduler_is_a_failure(sources, tmp_path):
    _need_dask()
    run = tmp_path / "a.h5"
    shutil.copy(sources[0], run)
    with socket.socket() as s:  # a loopback port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    p = _velab("fit", run, *FIT, "--scheduler", f"tcp://127.0.0.1:{port}")
    assert p.returncode == 5
    err = p.stderr.strip()
    assert err.startswith(f"velab: --scheduler tcp://127.0.0.1:{port}: cannot connect") and "\n" not in err
    assert _fits(run) == []


def test_lost_scheduler_fails_the_rest_and_leaves_no_half_written_file(sources, tmp_path):
    """The scheduler dies mid-batch: the fits that came back are saved, whole; the others are
    'scheduler lost' failures and their runs are byte-identical; exit code 5."""
    _need_dask()
    # enough runs that the scheduler dies mid-batch: 16 of these quick fits were all done on a quiet host before
    # the kill, sent at the first run's progress line, took effect (exit 0, no run lost)
    runs = _archive(sources, tmp_path / "lost", n=48)
    before = {p: _digest(p) for p in runs}
    proc, address = _start_cluster()
    try:
        client = subprocess.Popen([sys.executable, "-m", "velab.cli", "-v", "fit", *map(str, runs),
                                   "--models", "0-2", "--window", "2", "--starts", "2", "--scheduler", address,
                                   "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for line in client.stderr:  # -v off a terminal: one progress line per run done
            if "velab fit [" in line:
                break
        os.killpg(proc.pid, signal.SIGKILL)  # the scheduler and its workers, mid-batch
        out, err = client.communicate(timeout=120)
    finally:
        _stop_cluster(proc)
    assert client.returncode == 5, err
    doc = json.loads(out)
    lost = [r for r in doc["runs"] if r["status"] == "failed"]
    assert lost and all(r["reason"] == "scheduler lost" and r["exit_code"] == 5 for r in lost)
    assert doc["batch"]["fitted"] >= 1  # the first fit came back before the kill
    for r in doc["runs"]:
        p = Path(r["path"])
        if r["status"] == "saved":
            assert _stored(p)["best"] == r["best"]  # a whole fit group
        else:
            assert _digest(p) == before[p]
    assert not [f for f in os.listdir(tmp_path / "lost") if f.startswith(".")]
    assert "Traceback" not in err and f"velab: FAILED {lost[0]['path']} (scheduler lost): " in err


# ------------------------------------------------------------------- a worker process that dies



def test_a_dying_worker_process_fails_only_its_run(sources, tmp_path):
    """--jobs 2: the fit process fitting crash.h5 is killed (as a crash in a library would end it), and again
    when that run is tried once more in a fresh process: that run is "worker lost", the others are fitted."""
    from velab.batch.runner import run_batch
    from velab.cli import build_parser
    from velab.commands.fit import _options, fit_request
    from velab.fitservice import FitService

    files = _archive(sources, tmp_path / "die", n=5)
    crash = files[2].with_name("crash.h5")
    files[2].rename(crash)
    files[2] = crash
    before = _digest(crash)
    opts = _options(build_parser().parse_args(["fit", "x.h5", *FIT]))
    service = FitService.processes(2)
    kills: list[int] = []

    def killer():
        end = time.monotonic() + 240
        while len(kills) < 2 and time.monotonic() < end:
            for pid, request in service.backend.running():
                if request.source.path == str(crash) and pid not in kills:
                    os.kill(pid, signal.SIGKILL)
                    kills.append(pid)
            time.sleep(0.005)
    threading.Thread(target=killer, daemon=True).start()
    batch = run_batch(fit_request, [str(p) for p in files], opts, service=service)
    assert len(kills) == 2
    by = {Path(o["path"]).name: o for o in batch.outcomes}
    assert by["crash.h5"]["reason"] == "worker lost" and by["crash.h5"]["exit_code"] == 5
    assert "died (twice" in by["crash.h5"]["error"]
    assert _digest(crash) == before
    for p in files:
        if p != crash:
            assert by[p.name]["status"] == "saved" and FIT_NAME in _fits(p)
