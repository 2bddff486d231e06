"""The fit in a process of its own (velab.fit_worker): the same result as in this process, bit for
bit; every outcome named when the process dies, is cancelled or the fit fails; the recorder's final fit
survives the loss of its process; a halt ends the process at once."""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest

from record_helpers import assert_halted_fit, run_bounded
from velab.config import load_rig
from velab import fit_worker as worker
from velab.fitting.entry import fit_record
from velab.model import valve_head
from velab.recording import Recorder, RecordSettings


def _record(rate=1000.0, window=4.0, pre=1.0, seed=3):
    """A head record on the run's axis (absolute head, baseline before the trigger at t = pre)."""
    rig = load_rig("perugia")
    from velab.config import load_material

    t = np.arange(int((pre + window + 0.5) * rate)) / rate
    h = rig.steady_head_m + valve_head(t - pre, rig, load_material("A"))
    h += np.random.default_rng(seed).normal(0.0, 0.05, t.size)
    return rig, t, h, pre


def _kwargs(**kw):
    rig, t, h, pre = _record()
    base = dict(t_s=t, head_m=h, trigger_time_s=pre, rig=rig, window_s=4.0, record_rate_hz=1000.0,
                models=[0, 1, 2], method="auto")
    return base | kw


@pytest.fixture
def proc():
    p = worker.FitProcess()
    assert p.wait_ready(), "the fit process did not start"
    yield p
    p.close()


def test_fit_in_the_worker_is_the_fit_here_bit_for_bit(proc):
    kw = _kwargs()
    job, fut = proc.submit(**kw)
    there = fut.result(timeout=120)
    here = fit_record(**kw)
    assert [m.name for m in there.models] == [m.name for m in here.models] and there.best.name == here.best.name
    for a, b in zip(there.models, here.models):
        assert a.F == b.F and a.wave_speed_m_s == b.wave_speed_m_s
        assert np.array_equal(a.tau_s, b.tau_s) and np.array_equal(a.E_pa, b.E_pa)
    assert there.settings["record"] == here.settings["record"]
    assert not proc.busy and proc.alive  # ready for the next job


def test_a_fit_error_is_named_and_the_worker_goes_on(proc):
    _, fut = proc.submit(**_kwargs(window_s=60.0))  # longer than the record
    with pytest.raises(RuntimeError, match=r"DataError: fit window 60 s is longer than the record"):
        fut.result(timeout=60)
    _, fut = proc.submit(**_kwargs(models=[0]))
    assert fut.result(timeout=60).best.name == "EL"


def test_a_killed_worker_fails_its_job_with_the_signal(proc):
    _, fut = proc.submit(**_kwargs(models=[0, 1, 2, 3, 4]))
    # stopped at once, so the job cannot finish before the kill (a sleep let a fast fit end first)
    os.kill(proc.pid, signal.SIGSTOP)
    assert not fut.done()
    os.kill(proc.pid, signal.SIGKILL)
    with pytest.raises(worker.WorkerDied, match="killed by signal 9"):
        fut.result(timeout=10)
    assert not proc.alive
    _, late = proc.submit(**_kwargs())  # a dead worker refuses at once, naming why
    with pytest.raises(worker.WorkerDied):
        late.result(timeout=1)


def test_a_cancelled_job_ends_at_its_next_model(proc):
    job, fut = proc.submit(**_kwargs(models=[0, 1, 2, 3, 4]))
    proc.cancel(job)
    with pytest.raises(worker.Cancelled):
        fut.result(timeout=30)
    _, fut = proc.submit(**_kwargs(models=[0]))  # the process goes on serving
    assert fut.result(timeout=60).best.name == "EL"


def test_pool_keeps_an_idle_worker_and_replaces_a_dead_one():
    a = worker.acquire()
    assert a.wait_ready()
    worker.release(a)
    b = worker.acquire()
    assert b is a  # kept for the next run: no second start-up
    b.kill("test")
    worker.release(b)
    c = worker.acquire()
    assert c is not b and c.wait_ready()
    worker.release(c)


def _settings(tmp_path, **kw):
    return RecordSettings(**(dict(duration_s=5.0, fit_window_s=4.0, pretrigger_s=0.5, fit_models=(0, 1, 2, 3),
                                  out_dir=tmp_path, stall_timeout_s=3.0) | kw))


def _on_window_closed(rec, action):
    """Run ``action()`` on a thread of its own when the fit window closes (the final fit starts)."""
    def listen(ev):
        if ev.kind == "message" and "fit window closed" in str(ev.data):
            threading.Thread(target=action, daemon=True).start()
    rec.add_listener(listen)


def _busy_workers(timeout=30.0):
    """The fit processes computing a job, as soon as one is (a fresh fit process's imports take seconds on a
    loaded host before it takes the final fit: 5 s was too short at load 6)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        ws = [w for w in list(worker._live) if w.alive and w.busy]
        if ws:
            return ws
        time.sleep(0.01)
    return []


def test_the_final_fit_survives_the_loss_of_its_process(tmp_path):
    rec = Recorder.simulated(_settings(tmp_path), "default", material="A", clock="fast")
    messages = []
    rec.add_listener(lambda ev: messages.append(str(ev.data)) if ev.kind == "message" else None)

    def kill():
        for w in _busy_workers():
            os.kill(w.pid, signal.SIGKILL)
    _on_window_closed(rec, kill)
    out = run_bounded(rec, deadline_s=120)
    s = out.summary
    assert s.status == "completed", s.reason
    assert s.fit is not None, s.fit_error  # fitted in the recorder's process instead
    assert any("fit process lost" in m and "fitting in the recorder's process" in m for m in messages), messages
    # the same fit as velab fit of the file
    from velab.fitting import fit_run
    from velab.runfiles import read_run

    offline = fit_run(read_run(s.path), 4.0, models=[0, 1, 2, 3])
    assert [m.F for m in offline.models] == [m.F for m in s.fit.models]


def test_a_halt_during_the_final_fit_ends_its_process_at_once(tmp_path):
    rec = Recorder.simulated(_settings(tmp_path, fit_models=(0, 1, 2, 3, 4, 5, 6)), "default", material="A",
                             clock="fast")
    seen = {}

    def halt():
        seen["busy"] = _busy_workers()
        t0 = time.monotonic()
        rec.halt()
        seen["halt_s"] = time.monotonic() - t0
    _on_window_closed(rec, halt)
    out = run_bounded(rec, deadline_s=120)
    assert_halted_fit(out.summary, seen["halt_s"], seen["busy"])


def test_the_fit_in_the_recorder_s_process_when_asked(tmp_path):
    before = set(map(id, worker._live))
    rec = Recorder.simulated(_settings(tmp_path, fit_process=False, fit_models=(0, 1)), "default", material="A",
                             clock="fast")
    out = run_bounded(rec, deadline_s=120)
    assert out.summary.status == "completed" and out.summary.fit is not None, (out.summary.status, out.summary.reason)
    assert not [w for w in worker._live if id(w) not in before]  # no process started for it
