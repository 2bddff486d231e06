"""velab.recording.online_fit alone: the scheduling of the online fit around a stand-in fitter (the
fit path's fit_record / fit_lead replaced, in this process): the final fit's result and latency, a
quick fit skipped while another runs, a halt during a fit, a failing fit, a refusal said once."""

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
    """fit_record / fit_lead: returns at once, or blocks until ``release`` (calling ``progress`` as a
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
        monkeypatch.setattr(entry, "fit_lead", f)
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
    assert f.calls[0]["window_s"] == 2.0 and f.calls[0]["models"] == [1, 2, 3] and f.calls[0]["lead"] is True


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
    assert fit.lead_window_s() is None  # the sections' fit has no lead part
    assert OnlineFit(load_rig("perugia"), s, 1000.0, None, None).lead_window_s() is not None
    fit.start(T, H, 0.0, 0.5, final=False, section_heads={"mid": H + 1})  # no quick variant: skipped
    assert not f.calls and not fit.busy
    fit.start(T, H, 0.0, 2.0, final=True, section_heads={"mid": H + 1})
    assert fit.wait(5.0) and fit.result is not None
    (kw,) = f.calls
    assert set(kw["section_heads"]) == {"mid"} and kw["section_heads"]["mid"] is not None
    assert kw["rig"].name == load_rig("perugia_two_sections").name and "polish" not in kw
    assert [(k, d["final"]) for k, d in events] == [("fit", True)]


def test_the_fit_paths_sections_search_refuses_the_single_sweeps_options():
    from velab.errors import DataError

    with pytest.raises(DataError, match="polish = False: not for a fit of several sections"):
        entry.fit_record(T, H, 0.0, load_rig("perugia_two_sections"), 1.0, record_rate_hz=1000.0,
                           section_heads={"mid": H}, polish=False)
    with pytest.raises(DataError, match="sections: no head for mid"):  # (velab.fitting.sections says which)
        entry.fit_record(T, H, 0.0, load_rig("perugia_two_sections"), 1.0, record_rate_hz=1000.0)
