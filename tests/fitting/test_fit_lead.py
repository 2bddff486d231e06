"""The fit path's lead fit (velab.fitting.lead): the sweep of the window's first part, then a
continuation on the whole window. The recorder runs the lead while the window's last part is
being recorded and the final fit continues from it; ``velab fit`` computes the same lead from the
file and gets the same result exactly; a lead that is not this fit's is computed again; the
continuation names the same model as a one-step sweep on time-domain truths; a halt during the
lead ends the run with a named outcome."""

from __future__ import annotations

import copy
import os
import signal
import threading
import time

import numpy as np
import pytest

from record_helpers import CWF, assert_halted_fit, fast_sim, rate_clock, recorder, run_bounded
from test_fit_truths import SIGMA, _record as truth_record
from velab import fit_worker as worker
from velab.commands.fit import fit_file
from velab.config import load_material, load_rig
from velab.fitting import fit_lead, fit_record, fit_run
from velab.fitting.lead import LEAD_SHARE, MAX_LEAD_SHARE, MIN_LEAD_PERIODS, lead_window_s
from velab.fitting.options import FitOptions
from velab.fitting.results import SweepResult
from velab.model import valve_head
from velab.recording import Recorder, RecordSettings
from velab.recording.online_fit import HALTED
from velab.runfiles.reader import read_run
from velab.runfiles.summary import read_fits
from velab.simulators.bench import load_sim_config
from velab.fitting.report import format_report

WINDOW_S = 8.0  # the reference rig's period is 1.16 s: the lead holds 5 periods, 5.8 s (more than half the window)
MODELS = [0, 1, 2, 3]


def _same(a: SweepResult, b: SweepResult) -> None:
    assert [m.name for m in a.models] == [m.name for m in b.models] and a.best.name == b.best.name
    for x, y in zip(a.models, b.models):
        assert x.F == y.F and x.wave_speed_m_s == y.wave_speed_m_s, x.name
        assert np.array_equal(x.tau_s, y.tau_s) and np.array_equal(x.E_pa, y.E_pa), x.name


def _record(rate=1000.0, window=WINDOW_S, pre=1.0, seed=5):
    rig = load_rig("perugia")
    t = np.arange(int((pre + window + 0.5) * rate)) / rate
    h = rig.steady_head_m + valve_head(t - pre, rig, load_material("A"))
    h += np.random.default_rng(seed).normal(0.0, 0.05, t.size)
    return rig, dict(t_s=t, head_m=h, trigger_time_s=pre, rig=rig, record_rate_hz=rate, models=MODELS)


def test_which_fits_have_a_lead():
    perugia, imperial = load_rig("perugia"), load_rig("imperial")
    # half the window: the recorder runs the lead while the second half is recorded
    assert lead_window_s(perugia, 20.0, FitOptions()) == 20.0 * LEAD_SHARE == 10.0
    assert lead_window_s(perugia, 20.0, FitOptions(models=(0, 1), method="auto")) == 10.0
    # at least MIN_LEAD_PERIODS wave periods: more than half of a shorter window
    period = 4 * imperial.pipe.length_m / imperial.nominal_wave_speed_m_s
    assert lead_window_s(imperial, 20.0, FitOptions()) == pytest.approx(MIN_LEAD_PERIODS * period)
    assert MIN_LEAD_PERIODS * period > 10.0
    assert lead_window_s(imperial, 20.0, FitOptions()) <= MAX_LEAD_SHARE * 20.0
    # too few wave periods in the window's first MAX_LEAD_SHARE: one step
    assert lead_window_s(imperial, 15.0, FitOptions()) is None and lead_window_s(perugia, 4.0, FitOptions()) is None
    # only the default search: another method, no polish or capped starts are one step
    for opts in (FitOptions(method="nelder-mead"), FitOptions(polish=False), FitOptions(starts=2)):
        assert lead_window_s(perugia, 20.0, opts) is None, opts


def test_a_continuation_from_the_lead_is_the_fit_path_s_result():
    rig, kw = _record()
    whole = fit_record(window_s=WINDOW_S, **kw)
    lw = lead_window_s(rig, WINDOW_S, FitOptions())
    assert whole.settings["lead"]["window_s"] == pytest.approx(lw, abs=1.5e-3)  # (whole samples)
    assert whole.settings["lead"]["computed_in_this_fit"] is True
    # the lead made first (as the recorder does, on the samples up to its end) and handed over
    t, h = kw["t_s"], kw["head_m"]
    part = t < 1.0 + lw
    lead = fit_lead(**(kw | {"t_s": t[part], "head_m": h[part]}), window_s=WINDOW_S)
    assert lead.window_s == pytest.approx(lw, abs=1.5e-3)
    assert lead.settings["record"]["window_s"] == pytest.approx(lw, abs=1.5e-3)
    given = fit_record(window_s=WINDOW_S, lead=lead, **kw)
    assert given.settings["lead"]["computed_in_this_fit"] is False
    _same(given, whole)
    # a lead made for another fit (another window, other models) is not used: computed again
    for other in (fit_lead(window_s=WINDOW_S + 0.5, **kw), fit_lead(window_s=WINDOW_S, **(kw | {"models": [0, 1]}))):
        again = fit_record(window_s=WINDOW_S, lead=other, **kw)
        assert again.settings["lead"]["computed_in_this_fit"] is True
        _same(again, whole)
    # one step on request (comparisons): no lead
    assert fit_record(window_s=WINDOW_S, lead=False, **kw).settings["lead"] is None
    # a window too short for a lead: one step, and no lead to make
    assert fit_lead(window_s=4.0, **kw) is None and fit_record(window_s=4.0, **kw).settings["lead"] is None


def test_the_fit_process_runs_the_lead(tmp_path):
    rig, kw = _record()
    proc = worker.FitProcess()
    try:
        assert proc.wait_ready()
        _, fut = proc.submit("lead", window_s=WINDOW_S, **kw)
        there = fut.result(timeout=120)
    finally:
        proc.close()
    here = fit_lead(window_s=WINDOW_S, **kw)  # (one lead here: the same call twice gave the same result)
    _same(there, here)
    assert there.settings["lead_for"] == here.settings["lead_for"]


@pytest.mark.parametrize("rig_name,truth", [("perugia", "S3"), ("imperial", "S2")])
def test_the_continuation_names_what_a_one_step_sweep_names(rig_name, truth):
    """Time-domain (MOC, quadratic friction) truths: the lead + continuation and a one-step sweep
    end in the same basins: the same best model (the truth), F of every model within 1e-4 (1e-2 for
    models more than 10 AIC units behind)."""
    rig = load_rig(rig_name)
    t, h = truth_record(rig, truth, seed=5)
    kw = dict(t_s=t, head_m=h + rig.steady_head_m, trigger_time_s=0.0, rig=rig, window_s=20.0, record_rate_hz=1000.0)
    two = fit_record(**kw)
    one = fit_record(lead=False, **kw)
    assert two.settings["lead"] is not None and one.settings["lead"] is None
    assert two.best.name == one.best.name == truth, format_report(two, elements=False)
    # (well inside the wave speed's standard error: the two steps agree far below what the record can tell)
    assert abs(two.best.wave_speed_m_s - one.best.wave_speed_m_s) < 0.75 * one.best.wave_speed_se_m_s
    assert two.best.F / SIGMA**2 <= 1.05
    # the fitted closure (velab.fitting.manoeuvre) is refined with the best wall over the lead's 16 s in
    # two steps and over the whole 20 s in one: the models land a little apart (measured: the best within
    # 2e-5 of F, models thousands of AIC units away within 1.2e-3: their misfit depends on the closure)
    for a, b in zip(one.models, two.models):
        tol = 1e-4 if a.delta_aic <= 10 else 1e-2
        assert abs(b.F / a.F - 1) < tol, (a.name, a.F, b.F)


def _settings(tmp_path, rate, **kw):
    return RecordSettings(**(dict(duration_s=WINDOW_S, fit_window_s=WINDOW_S, pretrigger_s=1.5, sample_rate_hz=rate,
                                  fit_models=tuple(MODELS), out_dir=tmp_path, stall_timeout_s=3.0) | kw))


@pytest.mark.parametrize("rate", [1000.0, 10000.0])
def test_the_recorder_s_lead_is_the_final_fit_s_and_velab_fit_reproduces_it(tmp_path, rate):
    rec = Recorder.simulated(_settings(tmp_path, rate), "default", material="A", clock=rate_clock(rate))
    fits = []
    rec.add_listener(lambda ev: fits.append(ev.data) if ev.kind == "fit" else None)
    out = run_bounded(rec, deadline_s=120)
    s = out.summary
    assert s.status == "completed", s.reason
    assert s.fit is not None, s.fit_error
    leads = [f for f in fits if f.get("lead")]
    lw = lead_window_s(load_rig("perugia"), WINDOW_S, FitOptions())
    assert len(leads) == 1 and not leads[0]["final"] and leads[0]["window_s"] == pytest.approx(lw, abs=1.5e-3)
    # no quick fit at 75 % of the window: the lead (at 73 %) would cancel it
    assert all(f["window_s"] <= 0.5 * WINDOW_S + 1e-9 for f in fits if not f["final"] and not f.get("lead")), fits
    online = SweepResult.from_dict(read_fits(s.path)["online"])
    assert online.settings["lead"]["computed_in_this_fit"] is False  # the recorder's lead was used
    assert online.settings["lead"]["best"] == leads[0]["result"].best.name
    offline, _ = fit_file(str(s.path), {
        "models": MODELS, "window_s": WINDOW_S, "method": "auto", "reduced": False, "starts": None,
        "polish": True, "save": False, "name": None, "plot": None, "tau_min_s": None, "tau_max_s": None,
        "selection": "ar1", "friction": None, "friction_unsteady": None})
    assert offline.settings["lead"]["computed_in_this_fit"] is True
    assert offline.settings["record"] == online.settings["record"]
    _same(offline, online)


def _when_the_lead_runs(action, timeout=60.0):
    """Call ``action(busy workers)`` on a thread of its own as soon as a fit process is busy: with no
    intermediate fits, the first job of the run is the lead fit."""
    def watch():
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            busy = [w for w in list(worker._live) if w.alive and w.busy]
            if busy:
                action(busy)
                return
            time.sleep(0.002)
    threading.Thread(target=watch, daemon=True).start()


def test_a_halt_during_the_lead_fit_is_a_named_outcome(tmp_path):
    rec = Recorder.simulated(_settings(tmp_path, 1000.0, duration_s=12.0, fit_window_s=12.0, intermediate_fits=False,
                                       fit_models=(0, 1, 2, 3, 4, 5, 6)), "default", material="A", clock="fast")
    seen = {}

    def halt(busy):
        seen["busy"] = busy  # the lead, computing
        t0 = time.monotonic()
        rec.halt()
        seen["halt_s"] = time.monotonic() - t0

    _when_the_lead_runs(halt)
    out = run_bounded(rec, deadline_s=60)
    assert out.summary.fit_error == HALTED, (out.summary.status, out.summary.reason)  # (a loaded pair: failed, why?)
    assert_halted_fit(out.summary, seen["halt_s"], seen["busy"])


def test_a_lead_lost_with_its_process_is_computed_by_the_final_fit(tmp_path):
    rec = Recorder.simulated(_settings(tmp_path, 1000.0, duration_s=12.0, fit_window_s=12.0, intermediate_fits=False),
                             "default", material="A", clock="fast")
    messages, seen = [], {}

    def kill(busy):
        for w in busy:
            os.kill(w.pid, signal.SIGKILL)
        seen["killed"] = True

    rec.add_listener(lambda ev: messages.append(str(ev.data)) if ev.kind == "message" else None)
    _when_the_lead_runs(kill)
    out = run_bounded(rec, deadline_s=120)
    s = out.summary
    assert seen.get("killed")
    assert s.status == "completed", s.reason
    assert s.fit is not None, s.fit_error
    assert any("fit process lost" in m for m in messages), messages
    online = SweepResult.from_dict(read_fits(s.path)["online"])
    assert online.settings["lead"]["computed_in_this_fit"] is True  # the lead died with its process
    _same(fit_run(read_run(s.path), 12.0, models=MODELS), online)


def test_a_fault_after_the_lead_started_shortens_the_window_and_the_lead_is_made_again(tmp_path):
    """A stuck transducer 11 s after the trigger, once the lead (made for 12 s: its first 6 s) has
    started: the final window is the clean 11 s before it, the recorder's lead is not that fit's, and
    the final fit computes its own; the run is marked, and velab fit of the file over the window the
    online fit used reproduces it."""
    _, doc = load_sim_config("default")
    doc = copy.deepcopy(dict(doc))
    doc["faults"] = {"schedule": [{"device": "rig", "fault": {"stuck_channels": [0]}, "at": "trigger+11.0",
                                   "duration_s": 0.3}]}
    s = _settings(tmp_path, 1000.0, duration_s=12.5, fit_window_s=12.0, intermediate_fits=False)
    rec = recorder(fast_sim(doc), s)
    fits = []
    rec.add_listener(lambda ev: fits.append(ev.data) if ev.kind == "fit" else None)
    out = run_bounded(rec, deadline_s=120)
    summary = out.summary
    assert summary.status == CWF, (summary.status, summary.reason)
    assert summary.fit is not None, summary.fit_error
    assert [f["window_s"] for f in fits if f.get("lead")] == [pytest.approx(6.0)]  # the lead ran, for 12 s
    online = SweepResult.from_dict(read_fits(summary.path)["online"])
    w = online.settings["record"]["window_s"]
    assert 10.5 < w < 11.5  # shortened to the clean part before the stuck samples
    assert online.settings["lead"]["computed_in_this_fit"] is True
    assert online.settings["lead"]["window_s"] == pytest.approx(lead_window_s(load_rig("perugia"), w, FitOptions()),
                                                                   abs=1.5e-3)  # (whole samples)
    _same(fit_run(read_run(summary.path), w, models=MODELS), online)
