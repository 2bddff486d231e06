"""velab.recording.online_fit alone: the scheduling of the online fit around a stand-in fitter (the
fit path's fit_record replaced, in this process): the final fit's result and latency, a
quick fit skipped while another runs, a halt during a fit, a failing fit, a refusal said once; the final
outcome delivered once as a message (FitOutcome); and on the real fit service (velab.fitservice): the fit in
its process is fit_record of the same samples bit for bit, a process killed during the final fit hands it
to the recorder's process, and the run says so."""

from __future__ import annotations

import threading
from types import SimpleNamespace

import numpy as np
import pytest

from velab.config import load_rig
from velab.fitting import entry
from velab.recording.online_fit import HALTED, OnlineFit
from velab.recording.settings import RecordSettings

T = np.arange(-500, 2000) / 1000.0
H = np.full(T.size, 30.0)


class StandInFitter:
    """fit_record: returns at once, or blocks until ``release`` (calling ``progress`` as a
    real fit does between models), or raises ``error``."""

    def __init__(self, block=False, error=None):
        self.calls, self.release, self.block, self.error = [], threading.Event(), block, error
        self.started = threading.Event()

    def __call__(self, progress=None, **kw):
        self.calls.append(kw)
        self.started.set()
        while self.block and not self.release.wait(0.005):
            progress(0, 7, "S1")
        progress(7, 7, "S6")  # (a real fit reports after its last model too)
        if self.error:
            raise self.error
        return SimpleNamespace(window_s=kw["window_s"], best=SimpleNamespace(name="S3"))


@pytest.fixture
def fitter(monkeypatch):
    def use(**kw):
        f = StandInFitter(**kw)
        monkeypatch.setattr(entry, "fit_record", f)
        return f
    return use


def make():
    s = RecordSettings(fit=True, fit_process=False, fit_window_s=2.0, fit_models=(1, 2, 3))
    events, messages = [], []
    fit = OnlineFit(load_rig("perugia"), s, 1000.0, lambda k, d: events.append((k, d)), messages.append)
    return fit, events, messages


def test_the_final_fit_gives_the_result_its_latency_and_one_event(fitter):
    f = fitter()
    fit, events, _ = make()
    fit.start(T, H, 0.0, 2.0, final=True)
    assert fit.wait(5.0) and fit.result is not None and fit.latency_s >= 0.0 and not fit.error
    assert [(k, d["final"], d["window_s"]) for k, d in events] == [("fit", True, 2.0)]
    assert f.calls[0]["window_s"] == 2.0 and f.calls[0]["options"].models == (1, 2, 3)


def test_a_quick_fit_is_skipped_while_another_runs_and_gives_way_to_the_final(fitter):
    f = fitter(block=True)
    fit, events, _ = make()
    fit.start(T, H, 0.0, 0.5, final=False)
    assert f.started.wait(5.0) and fit.busy
    fit.start(T, H, 0.0, 1.0, final=False)  # busy: skipped
    assert len(f.calls) == 1
    fit.start(T, H, 0.0, 2.0, final=True)  # the quick one is cancelled at its next model
    f.release.set()
    assert fit.wait(5.0) and fit.result is not None
    assert [d["final"] for k, d in events] == [True]  # the cancelled quick fit published nothing


def test_a_halt_during_the_final_fit_is_its_named_outcome(fitter):
    f = fitter(block=True)
    fit, events, _ = make()
    fit.start(T, H, 0.0, 2.0, final=True)
    assert f.started.wait(5.0)
    fit.cancel()
    assert fit.wait(5.0) and fit.result is None and fit.error == HALTED and not events


def test_a_failing_fit_is_the_runs_fit_error(fitter):
    fitter(error=ValueError("singular matrix"))
    fit, events, messages = make()
    fit.start(T, H, 0.0, 2.0, final=True)
    assert fit.wait(5.0) and fit.result is None
    assert fit.error == "fit failed: ValueError: singular matrix" and messages == [fit.error] and not events


def test_the_first_refusal_is_the_one_said():
    fit, _, messages = make()
    fit.refuse("no fit: the run ended before the trigger")
    fit.refuse("no fit: something else")
    assert fit.error == messages[0] == "no fit: the run ended before the trigger" and len(messages) == 1
    assert fit.wait(0.01)  # no final fit started: nothing to wait for


def test_a_rig_with_several_sections_fits_them_all_in_the_final_fit_only(fitter):
    f = fitter()
    s = RecordSettings(fit=True, fit_process=False, fit_window_s=20.0, fit_models=(1, 2, 3))
    events = []
    fit = OnlineFit(load_rig("perugia_two_sections"), s, 1000.0, lambda k, d: events.append((k, d)), lambda m: None)
    fit.start(T, H, 0.0, 0.5, final=False, section_heads={"mid": H + 1})  # no quick variant: skipped
    assert not f.calls and not fit.busy
    fit.start(T, H, 0.0, 2.0, final=True, section_heads={"mid": H + 1})
    assert fit.wait(5.0) and fit.result is not None
    (kw,) = f.calls
    assert set(kw["section_heads"]) == {"mid"} and kw["section_heads"]["mid"] is not None
    assert kw["rig"].name == load_rig("perugia_two_sections").name and kw["options"].default_search
    assert [(k, d["final"]) for k, d in events] == [("fit", True)]


def test_the_fit_paths_sections_search_says_which_head_is_missing():
    from velab.errors import DataError

    with pytest.raises(DataError, match="sections: no head for mid"):  # (velab.fitting.sections says which)
        entry.fit_record(T, H, 0.0, load_rig("perugia_two_sections"), 1.0, record_rate_hz=1000.0)


# ------------------------------------------------------------------ the outcome as a message; the real fit service


def test_the_final_outcome_is_delivered_once_as_a_message(fitter):
    fitter()
    s = RecordSettings(fit=True, fit_process=False, fit_window_s=2.0, fit_models=(1, 2, 3))
    delivered = []
    fit = OnlineFit(load_rig("perugia"), s, 1000.0, lambda k, d: None, lambda m: None,
                    deliver=delivered.append)
    fit.start(T, H, 0.0, 2.0, final=True)
    assert fit.wait(5.0)
    fit.refuse("no fit: too late")  # the outcome is known: nothing more is said or delivered
    (outcome,) = delivered
    assert outcome.result is not None and outcome.error == "" and outcome.latency_s >= 0 and outcome.window_s == 2.0


def test_a_refusal_is_delivered_once():
    delivered = []
    s = RecordSettings(fit=True, fit_process=False, fit_window_s=2.0, fit_models=(1,))
    fit = OnlineFit(load_rig("perugia"), s, 1000.0, None, lambda m: None, deliver=delivered.append)
    threads = [threading.Thread(target=fit.refuse, args=(f"no fit: reason {i}",)) for i in range(8)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert len(delivered) == 1 and delivered[0].error.startswith("no fit: reason ")


def _real_record():
    from velab.config import load_material
    from velab.model import valve_head

    rig, rate, pre = load_rig("perugia"), 1000.0, 1.0
    t = np.arange(int((pre + 3.5) * rate)) / rate
    h = rig.steady_head_m + valve_head(t - pre, rig, load_material("A"))
    h += np.random.default_rng(3).normal(0.0, 0.05, t.size)
    return rig, t, h, pre


def _real_fit(**settings):
    rig, t, h, pre = _real_record()
    s = RecordSettings(fit=True, fit_window_s=3.0, fit_models=(0, 1), **settings)
    delivered, messages = [], []
    fit = OnlineFit(rig, s, 1000.0, lambda k, d: None, messages.append, deliver=delivered.append)
    return fit, delivered, messages, (rig, t, h, pre)


def test_the_online_fit_in_its_process_is_fit_record_of_the_same_samples_bit_for_bit():
    fit, delivered, messages, (rig, t, h, pre) = _real_fit(fit_process=True)
    fit.start_process()
    try:
        fit.start(t, h, pre, 3.0, final=True)
        assert fit.wait(180)
    finally:
        fit.close()
    (o,) = delivered
    assert o.result is not None, o.error
    here = entry.fit_record(t, h, pre, rig, 3.0, record_rate_hz=1000.0, models=[0, 1], method="auto")
    for a, b in zip(o.result.models, here.models):
        assert a.F == b.F and a.wave_speed_m_s == b.wave_speed_m_s and np.array_equal(a.tau_s, b.tau_s)
    assert not messages


def test_a_fit_process_killed_during_the_final_fit_hands_it_to_the_recorders_process():
    import os
    import signal
    import time

    fit, delivered, messages, (rig, t, h, pre) = _real_fit(fit_process=True)
    fit.start_process()
    try:
        fit.start(t, h, pre, 3.0, final=True)
        backend = fit._proc.backend
        end = time.monotonic() + 120
        while not backend.running() and time.monotonic() < end:
            time.sleep(0.005)
        (pid, _), = backend.running()
        os.kill(pid, signal.SIGKILL)
        assert fit.wait(180)
    finally:
        fit.close()
    (o,) = delivered
    assert o.result is not None, o.error
    assert any(m.startswith("fit process lost (") and "recorder's process" in m for m in messages), messages
