"""Calibration engine: Jacobian, parameter maps, criteria, data checks, warm start, threads."""

import math
import threading

import numpy as np
import pytest

from velab.config import load_material, load_rig
from velab.errors import DataError
from velab.fitting import SweepContext, fit_sweep, parse_models, support_category
from velab.fitting.engine import HeadEvaluator
from velab.fitting.params import ParamMap, bound_hits, creep_const, derive_bounds
from velab.fitting.results import ModelFit
from velab.fitting.selection import apply_criteria
from velab.fitting.data import lowpass_decimate, prepare_window
from velab.model import valve_head


@pytest.fixture(scope="module")
def rig():
    # data from the frequency model (linear friction): the fit must assume the same law
    return load_rig("perugia").with_changes(friction="linear")


@pytest.mark.parametrize("band", ["auto", None])
def test_analytic_jacobian_matches_finite_differences(rig, band):
    t = np.arange(3000) / 1000.0
    ev = HeadEvaluator(rig, t, band_hz=band)
    A = load_material("A")
    pm = ParamMap(3, derive_bounds(rig, 1e-3, 3.0))
    c = creep_const(rig) * A.wave_speed_m_s**2
    x = pm.pack(A.wave_speed_m_s, [c / e.E_pa for e in A.elements], [e.tau_s for e in A.elements])
    h, J = ev.head_jac_x(*pm.unpack(x))
    np.testing.assert_allclose(h, valve_head(t, rig, A, band_hz=band), atol=1e-10)
    for j in range(pm.size):
        dx = np.zeros(pm.size)
        dx[j] = 1e-6
        fd = (ev.head(*pm.unpack(x + dx)) - ev.head(*pm.unpack(x - dx))) / 2e-6
        assert np.max(np.abs(fd - J[j])) < 1e-5 * np.max(np.abs(J[j])) + 1e-9
    # a vanished element (J' at its lower bound) leaves the head of the smaller model
    pm4 = ParamMap(4, pm.bounds_)
    h4 = ev.head(*pm4.unpack(pm4.embed(pm, x)))
    assert np.max(np.abs(h4 - h)) < 1e-12


def test_split_evaluation_is_bit_identical(rig):
    """workers=2 (bins, then inverse-FFT rows, in two threads) gives exactly the one-thread result."""
    t = np.arange(12000) / 1000.0  # 6 000 full-band bins: above the split threshold
    one = HeadEvaluator(rig, t, band_hz=None)
    two = one.fork(workers=2)
    assert one.workers == 1 and two.workers == 2 and two.model is one.model
    rng = np.random.default_rng(3)
    for m in (0, 1, 4, 6):
        J, tau = rng.uniform(0.01, 0.2, m), np.geomspace(0.01, 5.0, m) if m else np.array([])
        for tau_free in (True, False):
            h1, J1 = one.head_jac_x(352.0, J, tau, tau_free)
            h2, J2 = two.head_jac_x(352.0, J, tau, tau_free)
            assert np.array_equal(h1, h2) and np.array_equal(J1, J2)
        assert np.array_equal(one.head(352.0, J, tau), two.head(352.0, J, tau))
    assert two.evaluations == one.evaluations == 12


def _split_head_in_child(q):
    t = np.arange(12000) / 1000.0
    ev = HeadEvaluator(load_rig("perugia"), t, band_hz=None, workers=2)
    q.put(float(ev.head(352.0, [0.1], [0.5])[-1]))


def test_split_evaluation_in_a_forked_child(rig):
    """The helper thread does not survive a fork: a child forked after the parent used it (velab fit
    --jobs, Dask's process workers) starts its own instead of queueing work for a thread that is not
    there (it hung)."""
    import multiprocessing

    t = np.arange(12000) / 1000.0
    parent = HeadEvaluator(load_rig("perugia"), t, band_hz=None, workers=2)
    expected = float(parent.head(352.0, [0.1], [0.5])[-1])  # the helper now runs in this process
    ctx = multiprocessing.get_context("fork")
    q = ctx.Queue()
    child = ctx.Process(target=_split_head_in_child, args=(q,))
    child.start()
    try:
        assert q.get(timeout=60) == expected
    finally:
        child.join(10)
        if child.is_alive():
            child.kill()
    assert child.exitcode == 0


def test_sweep_threads_give_the_same_result(rig):
    """threads=2 (split full-band evaluations, coarse starts shared out, two polish candidates at
    once) and threads=1 calibrate to exactly the same models."""
    t, h = _record(rig, "A")
    r1 = fit_sweep(t, h, rig, models="0-3", window_s=6.0, threads=1)
    r2 = fit_sweep(t, h, rig, models="0-3", window_s=6.0, threads=2)
    for a, b in zip(r1.models, r2.models):
        assert (a.name, a.F, a.wave_speed_m_s, a.E_pa, a.tau_s, a.evaluations) == \
            (b.name, b.F, b.wave_speed_m_s, b.E_pa, b.tau_s, b.evaluations)


def test_param_map_roundtrip_and_bounds(rig):
    b = derive_bounds(rig, 1e-3, 20.0)
    # data-derived retardation-time bounds: max(2 dt, closure / 10) and 10 windows
    assert b.tau_min_s == pytest.approx(max(2e-3, 0.1 * rig.manoeuvre.closure_time_s))
    assert b.tau_max_s == pytest.approx(200.0)
    assert derive_bounds(rig, 0.01, 20.0).tau_min_s == pytest.approx(0.02)
    assert derive_bounds(rig, 1e-3, 20.0, tau_min_s=0.002).tau_min_s == 0.002
    with pytest.raises(DataError, match="tau_min"):
        derive_bounds(rig, 1e-3, 20.0, tau_min_s=300.0)
    with pytest.raises(DataError, match="positive"):
        derive_bounds(rig, 1e-3, 20.0, tau_max_s=-1.0)
    from velab.rig import FitSettings

    b2 = derive_bounds(rig.with_changes(fit=FitSettings(tau_min_s=0.004, tau_max_s=50.0)), 1e-3, 20.0)
    assert (b2.tau_min_s, b2.tau_max_s) == (0.004, 50.0) and b2.sources["tau_min_s"] == "rig [fit] table"
    pm = ParamMap(2, b)
    x = pm.pack(350.0, [0.1, 0.01], [0.5, 0.05])
    a, J, tau = pm.unpack(x)
    assert a == pytest.approx(350.0) and np.allclose(J, [0.1, 0.01]) and np.allclose(tau, [0.5, 0.05])
    # outside the box: brought back inside
    a, J, tau = pm.unpack(pm.project(pm.pack(350.0, [1e-30, 1e6], [1e-6, 1e6])))
    assert J[0] == pytest.approx(b.J_rel_min) and J[1] == pytest.approx(b.J_rel_max)
    assert tau[0] == pytest.approx(b.tau_min_s) and tau[1] == pytest.approx(b.tau_max_s)
    red = ParamMap(2, b, fixed_tau=(0.01, 0.1))
    assert red.size == 3
    assert np.allclose(red.unpack(red.pack(350.0, [0.1, 0.2]))[2], [0.01, 0.1])
    # bound hits name the parameter, the bound and the option that moves it
    hits = bound_hits(pm, pm.project(pm.pack(350.0, [0.1, 0.01], [1e-6, 0.5])))
    assert [(h["parameter"], h["bound"], h["option"]) for h in hits] == [("tau_1", "lower", "--tau-min")]


def test_information_criteria_and_support():
    fits = [ModelFit(name=f"S{m}", m=m, k=2 * m + 1, reduced=False, n=1000, F=F, wave_speed_m_s=350.0,
                     E_pa=(), eta_pa_s=(), lag1_autocorr=0.0) for m, F in ((1, 0.02), (2, 0.01), (3, 0.01))]
    apply_criteria(fits)
    assert fits[1].aic == pytest.approx(1000 * math.log(0.01) + 10)
    assert fits[1].aicc == pytest.approx(fits[1].aic + 2 * 5 * 6 / (1000 - 5 - 1))
    assert fits[1].bic == pytest.approx(1000 * math.log(0.01) + 5 * math.log(1000))
    assert fits[1].delta_aic == 0 and fits[2].delta_aic == pytest.approx(4.0)
    assert sum(f.weight for f in fits) == pytest.approx(1.0)
    assert fits[2].weight / fits[1].weight == pytest.approx(math.exp(-2))
    assert [support_category(v) for v in (0, 1.9, 3, 5, 8, 11)] == [
        "substantial", "substantial", "moderate", "considerably less", "little", "essentially none"]


def test_parse_models():
    assert parse_models("0-6") == list(range(7))
    assert parse_models("1,3,5") == [1, 3, 5]
    assert parse_models(range(2)) == [0, 1]
    for bad in ("7", "a-b", "-1"):
        with pytest.raises(DataError):
            parse_models(bad)


def test_window_checks():
    t = np.arange(-100, 5000) / 1000.0
    h = np.zeros_like(t)
    tw, hw = prepare_window(t, h, 2.0)
    assert tw[0] == 0.0 and tw.size == 2000
    with pytest.raises(DataError, match="longer than the record"):
        prepare_window(t, h, 6.0)
    h[1000] = np.nan
    with pytest.raises(DataError, match="NaN"):
        prepare_window(t, h, 2.0)


def test_lowpass_keeps_band_and_removes_noise():
    n = 4000
    t = np.arange(n) / 1000.0
    slow = np.sin(2 * np.pi * 3 * t)
    noise = np.random.default_rng(0).normal(0, 1, n)
    d = lowpass_decimate(slow + noise, 10)
    assert d.size == 400
    # the in-band signal survives, 90 % of the white-noise power is removed
    assert np.var(d - slow[::10]) == pytest.approx(0.1, rel=0.2)


def _record(rig, material, seconds=6.0, seed=3):
    t = np.arange(-200, int(seconds * 1000)) / 1000.0
    h = valve_head(t, rig, load_material(material))
    return t, h + np.random.default_rng(seed).normal(0, 0.1, t.size)


def test_elastic_pipe_recovers_wave_speed_and_el_wins(rig):
    t, h = _record(rig, "elastic")
    r = fit_sweep(t, h, rig, models="0-1", window_s=5.0)
    el = r["EL"]
    true_a = load_material("elastic").wave_speed_m_s
    assert abs(el.wave_speed_m_s - true_a) < 0.5
    assert el.F == pytest.approx(0.01, rel=0.05)
    assert r.best.name == "EL"
    assert r["S1"].delta_aic > 0


def test_reduced_models_warm_start_and_threads(rig):
    t, h = _record(rig, "A")
    r = fit_sweep(t, h, rig, models="0-2", window_s=5.0, reduced=True)
    names = [f.name for f in r.models]
    assert names == ["EL", "S1", "S2", "S1r", "S2r"]
    s2r = r["S2r"]
    assert s2r.k == 3 and s2r.reduced and np.allclose(s2r.tau_s, [0.01, 0.1])
    assert r["S2"].F <= r["S1"].F * (1 + 1e-9)
    doc = r.to_dict()
    assert doc["best"] == r.best.name and doc["n"] == 5000
    # warm start from the previous result on a longer window (online use)
    calls = []
    r2 = fit_sweep(t, h, rig, models="0-2", window_s=5.5, context=SweepContext(initial=r), progress=lambda *a: calls.append(a))
    assert [c[2] for c in calls] == ["EL", "S1", "S2"] and calls[-1][:2] == (3, 3)
    assert r2.n == 5500 and r2["S2"].F == pytest.approx(r["S2"].F, rel=0.05)
    # thread safety: concurrent fits give the sequential result
    seq = fit_sweep(t, h, rig, models="1", window_s=4.0).models[0].F
    out = [None, None]

    def work(i):
        out[i] = fit_sweep(t, h, rig, models="1", window_s=4.0).models[0].F

    th = [threading.Thread(target=work, args=(i,)) for i in range(2)]
    for x in th:
        x.start()
    for x in th:
        x.join()
    assert out == [seq, seq]


@pytest.mark.parametrize("method", ["least-squares", "nelder-mead", "evolution"])
def test_other_methods_reach_the_same_s1(rig, method):
    t, h = _record(rig, "hdpe_s1", seconds=4.0)
    ref = fit_sweep(t, h, rig, models="1", window_s=3.0)
    r = fit_sweep(t, h, rig, models="1", window_s=3.0, method=method)
    assert r.method == method
    assert r["S1"].F == pytest.approx(ref["S1"].F, rel=1e-4)


def test_trigger_between_samples_still_names_the_truth():
    """A recording's trigger falls between two samples. The truth (material A,
    sampled 0.05 ms before the trigger, 4 mm noise) must still select S3: with the
    step placed on the next sample, S4 used to win by a ΔAIC of hundreds."""
    from velab.config import load_material, load_rig
    from velab.fitting import fit_sweep
    from velab.model import valve_head

    rig, mat = load_rig("perugia").with_changes(friction="linear"), load_material("A")
    tf = np.arange(0, 11, 2e-5)
    hf = valve_head(tf, rig, mat)
    t = np.arange(-200, 10000) * 1e-3 - 0.05e-3
    h = np.interp(t, tf, hf, left=0.0) + 0.004 * np.random.default_rng(7).standard_normal(t.size)
    r = fit_sweep(t, h, rig, models=[3, 4], window_s=10)
    assert r.best.name == "S3"
    assert r["S4"].delta_aic > 2
    assert abs(r["S3"].wave_speed_m_s - 353.73) < 0.5


def test_one_variable_is_solved_to_its_minimum_where_gauss_newton_crawls(rig):
    """EL on a creeping pipe's record: the residual is large, so Gauss-Newton converges only linearly
    (a few per cent of the way per step). The secant on dF/dx (Stage.lsq_1d) reaches the minimum:
    the gradient vanishes and F is no worse than Gauss-Newton's after the same budget."""
    from velab.fitting.solvers import Stage

    t = np.arange(20000) / 1000.0
    d = valve_head(t, rig, load_material("A")) + np.random.default_rng(3).normal(0, 0.1, t.size)
    stage = Stage(HeadEvaluator(rig, t, band_hz=None), d)
    pm = ParamMap(0, derive_bounds(rig, 1e-3, 20.0))
    a0 = fit_sweep(t, d, rig, models="0").best.wave_speed_m_s * 1.0002  # next to EL's optimum
    x0 = [math.log(a0)]
    gn = stage.lsq(pm, x0, max_nfev=40, ftol=1e-10, secant=False)
    before = stage.ev.evaluations
    sec = stage.lsq(pm, x0, max_nfev=40, ftol=1e-10)
    assert stage.ev.evaluations - before < 15
    assert sec.F <= gn.F
    h, (j,) = stage.ev.head_jac_x(*pm.unpack(sec.x))
    r = h - d
    # |dF/dx| relative to the curvature scale: the step to the minimum is below 1e-7 in ln a
    assert abs(np.dot(j, r)) / np.dot(j, j) < 1e-7


def test_equivalent_friction_on_the_coarse_grid_matches_the_full_band():
    """The sweep matches the linear resistance that stands in for quadratic friction on the coarse
    grid (low-passed time-domain head against the band-limited model): same factor as on the full
    band, to a few per cent (it only sets how fast the friction refresh converges)."""
    from velab.fitting.friction import equivalent_friction
    from velab.moc import moc_head

    qrig = load_rig("perugia").with_changes(friction="quadratic")
    t = np.arange(20000) / 1000.0
    A = load_material("A")
    c = creep_const(qrig) * A.wave_speed_m_s**2
    params = (A.wave_speed_m_s, np.array([c / e.E_pa for e in A.elements]), np.array([e.tau_s for e in A.elements]))
    h = moc_head(qrig, *params, t)
    full = equivalent_friction(HeadEvaluator(qrig, t, band_hz=None), params, h)
    q = 10
    coarse = equivalent_friction(HeadEvaluator(qrig, t[::q], band_hz="auto"), params, lowpass_decimate(h, q))
    assert 0.1 < full.factor(qrig) < 0.9  # well below the tangent R (physics.md section 9)
    assert coarse.factor(qrig) == pytest.approx(full.factor(qrig), rel=0.05)
