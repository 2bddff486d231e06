"""velab.fitservice: one fit, three backends. Each backend fits a small synthetic run (``velab synth``) and
gives what a direct call of the fitter gives; a cancel and a killed fit process end the Future with a
named exception within seconds; progress arrives as FitProgress messages; bad requests are one line."""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest

from velab.cli import main
from velab.errors import DataError
from velab.fitting.options import FitOptions
from velab.fitservice import (FitCancelled, FitProgress, FitRequest, FitService, FitWorkerDied, Record,
                              RunFile, RunFiles)

WINDOW_S = 1.5
CHOICES = FitOptions(models=(0, 1), starts=2)  # the plumbing, not the science: two models, two starts


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    d = tmp_path_factory.mktemp("fitservice")
    out = []
    for seed in (1, 2):
        p = d / f"run{seed}.h5"
        assert main(["synth", "--material", "A", "--duration", "2", "--rate", "200", "--seed", str(seed),
                     "-o", str(p), "-q"]) == 0
        out.append(p)
    return out


def _direct(path):
    from velab.fitting import fit_run
    from velab.runfiles import read_run

    return fit_run(read_run(path), WINDOW_S, models=[0, 1], method="auto", starts=2)


def _same(a, b) -> None:
    assert [m.name for m in a.models] == [m.name for m in b.models] and a.best.name == b.best.name
    for x, y in zip(a.models, b.models):
        assert x.F == y.F and x.wave_speed_m_s == y.wave_speed_m_s, x.name
        assert np.array_equal(x.tau_s, y.tau_s) and np.array_equal(x.E_pa, y.E_pa), x.name


@pytest.fixture(scope="module")
def direct(runs):
    return _direct(runs[0])


def test_a_request_carries_the_fitters_own_options_checked_at_the_door():
    with pytest.raises(DataError, match="fit choices must be FitOptions"):
        FitRequest(RunFile("x.h5"), 20.0, {"models": [1]})
    with pytest.raises(DataError, match="bad model list"):
        FitOptions(models="9")
    for bad, match in (({"starts": 0}, "starts must be"), ({"selection": "bic"}, "selection 'bic'"),
                       ({"tau_min_s": 2.0, "tau_max_s": 1.0}, "must be below"), ({"friction": "x"}, "friction law 'x'")):
        with pytest.raises(DataError, match=match):
            FitOptions(**bad)
    with pytest.raises(DataError, match="window"):
        FitRequest(RunFile("x.h5"), window_s=-1.0)
    with pytest.raises(DataError, match="two or more runs"):
        RunFiles(("a.h5",))


@pytest.mark.parametrize("backend", ["thread", "process"])
def test_a_run_file_fit_is_the_direct_call_and_reports_progress(backend, runs, direct):
    service = FitService.in_thread() if backend == "thread" else FitService.processes(1, start=True)
    seen = []
    try:
        fut = service.submit(FitRequest(RunFile(runs[0]), WINDOW_S, CHOICES, label="a"), progress=seen.append)
        result = fut.result(timeout=120)
    finally:
        service.close()
    _same(result, direct)
    assert result.settings["window_s_requested"] == WINDOW_S
    assert seen and all(isinstance(m, FitProgress) and m.label == "a" for m in seen)
    assert seen[-1].done == seen[-1].total and {m.name for m in seen} >= {"S1"}
    assert fut.where.endswith(f":{os.getpid()}") == (backend == "thread") and fut.seconds > 0


def test_a_record_in_memory_is_fit_record_of_it(runs):
    from velab.fitting import fit_record
    from velab.runfiles import read_run

    run = read_run(runs[0])
    src = Record(run.time_s, run.head_m, run.trigger_time_s, run.rig, run.sample_rate_hz,
                 position_pct=run.channels.get("valve_position"))
    with FitService.processes(1) as service:
        there = service.submit(FitRequest(src, WINDOW_S, CHOICES)).result(timeout=120)
    here = fit_record(run.time_s, run.head_m, run.trigger_time_s, run.rig, WINDOW_S, record_rate_hz=run.sample_rate_hz,
                      position_pct=run.channels.get("valve_position"), models=[0, 1], method="auto", starts=2)
    _same(there, here)


def test_a_joint_fit_and_its_one_line_refusal(runs):
    from velab.fitting.joint import fit_joint
    from velab.jointfiles import read_sources

    service = FitService.in_thread()
    choices = FitOptions(models=(1,))
    result = service.submit(FitRequest(RunFiles(tuple(runs)), WINDOW_S, choices)).result(timeout=300)
    here = fit_joint(read_sources(runs, WINDOW_S), WINDOW_S, models=[1])
    _same(result, here)
    with pytest.raises(DataError) as e:
        service.submit(FitRequest(RunFiles(tuple(runs)), 30.0, choices)).result(timeout=60)
    assert "window" in str(e.value) and "\n" not in str(e.value)


def test_a_user_error_in_the_fit_process_comes_back_as_itself(runs):
    with FitService.processes(1) as service:
        with pytest.raises(DataError, match="window") as e:  # (a window longer than the record: the fit's own check)
            service.submit(FitRequest(RunFile(runs[0]), 500.0, CHOICES)).result(timeout=120)
        assert type(e.value) is DataError
        assert service.submit(FitRequest(RunFile(runs[0]), WINDOW_S, CHOICES)).result(timeout=120).best.name


SLOW = FitOptions(models=(0, 1, 2, 3, 4, 5, 6))  # long enough to be caught running


@pytest.mark.parametrize("backend", ["thread", "process"])
def test_a_cancel_ends_the_future_at_once_with_fit_cancelled(backend, runs):
    service = FitService.in_thread() if backend == "thread" else FitService.processes(1, start=True)
    started = threading.Event()
    try:
        fut = service.submit(FitRequest(RunFile(runs[0]), WINDOW_S, SLOW), progress=lambda m: started.set())
        assert started.wait(120)
        t0 = time.monotonic()
        assert fut.cancel()
        with pytest.raises(FitCancelled):
            fut.result(timeout=5)
        assert time.monotonic() - t0 < 1.0 and not fut.cancel()  # (over: nothing more to cancel)
        # the service goes on: the next fit runs (in the process, after the cancelled one's next model)
        assert service.submit(FitRequest(RunFile(runs[0]), WINDOW_S, CHOICES)).result(timeout=120).best.name
    finally:
        service.close()


def test_a_killed_fit_process_fails_its_fit_with_fit_worker_died_within_seconds(runs):
    with FitService.processes(1, start=True) as service:
        started = threading.Event()
        fut = service.submit(FitRequest(RunFile(runs[0]), WINDOW_S, SLOW), progress=lambda m: started.set())
        assert started.wait(120)
        (pid,) = service.backend.pids
        t0 = time.monotonic()
        os.kill(pid, signal.SIGKILL)
        with pytest.raises(FitWorkerDied, match="killed by signal 9"):
            fut.result(timeout=5)
        assert time.monotonic() - t0 < 5.0
        # replace_dead (the default): the next fit gets a new process
        again = service.submit(FitRequest(RunFile(runs[0]), WINDOW_S, CHOICES))
        assert again.result(timeout=120).best.name and not again.where.endswith(f":{pid}")


def test_without_replacement_a_dead_process_fails_the_next_fits_at_once(runs):
    with FitService.processes(1, start=True, replace_dead=False) as service:
        (pid,) = service.backend.pids
        os.kill(pid, signal.SIGKILL)
        deadline = time.monotonic() + 5
        while service.alive and time.monotonic() < deadline:
            time.sleep(0.01)
        assert not service.alive
        with pytest.raises(FitWorkerDied):
            service.submit(FitRequest(RunFile(runs[0]), WINDOW_S, CHOICES)).result(timeout=5)


def test_a_halt_kills_the_fit_process_at_once(runs):
    with FitService.processes(1, start=True) as service:
        started = threading.Event()
        fut = service.submit(FitRequest(RunFile(runs[0]), WINDOW_S, SLOW), progress=lambda m: started.set())
        assert started.wait(120)
        (pid,) = service.backend.pids
        assert fut.cancel_fit(kill=True)
        with pytest.raises(FitCancelled):
            fut.result(timeout=1)
        deadline = time.monotonic() + 5
        while pid in service.backend.pids and time.monotonic() < deadline:
            time.sleep(0.01)
        assert pid not in service.backend.pids


def test_on_a_dask_cluster(runs, direct):
    pytest.importorskip("distributed", reason="the velab[cluster] extra is not installed")
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1", scheduler_port=0,
                      dashboard_address=None) as cluster:
        with FitService.dask(cluster.scheduler_address) as service:
            fut = service.submit(FitRequest(RunFile(runs[0]), WINDOW_S, CHOICES))
            _same(fut.result(timeout=180), direct)
            assert fut.where and not fut.where.endswith(f":{os.getpid()}")
            with pytest.raises(DataError, match="window"):
                service.submit(FitRequest(RunFile(runs[0]), 500.0, CHOICES)).result(timeout=60)
