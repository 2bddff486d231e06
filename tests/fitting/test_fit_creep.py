"""The creep function J(t) - J0 of a calibrated model and its 95 % band (velab.fitting.creep).

The delta method's gradient against finite differences and against sampling; on data the fitter did
not make (the time-domain model with quadratic friction and the real butterfly valve on its sigmoid in
position, material A's S3, white noise 0.1 m, the recorded valve position) the true J(t) - J0 lies
inside the best model's band, and the band narrows with the noise; from the head alone (the closure
fitted as nuisance parameters, outside the covariance) it does not: a known gap, marked xfail; the
band survives JSON and the run file; a fit stored before the covariance was kept reads back with no
band; the report's lines.
"""

import json
import math

import h5py
import numpy as np
import pytest

from velab.commands.common import json_ready
from velab.config import load_material, load_rig
from velab.fitting.selection import averaged_creep
from velab.fitting.creep import (CREEP_POINTS, Z95, CreepCurve, creep_curve, creep_range, decades,
                                 log_creep_gradient,
                                 retarded_compliance)
from velab.fitting.params import creep_const
from velab.fitting.entry import fit_record
from velab.fitting.report import creep_lines
from velab.fitting.results import ModelFit, SweepResult
from velab.model import creep_scale
from velab.moc import moc_head
from velab.runfiles.fits import read_fit_group, write_fit_group
from velab.valvelaw import Valve, commanded_position_pct
from velab.fitting.report import format_report

SIGMA = 0.1
CHECK_TIMES = (0.05, 0.5, 5.0)


def _fit_of(J_per_pa, tau_s, a=353.73, cov=None, reduced=False) -> ModelFit:
    E = 1.0 / np.asarray(J_per_pa, dtype=float)
    m = E.size
    return ModelFit(name=f"S{m}", m=m, k=1 + (m if reduced else 2 * m), reduced=reduced, n=1000, F=0.01,
                    wave_speed_m_s=a, E_pa=tuple(E), eta_pa_s=tuple(E * np.asarray(tau_s)), lag1_autocorr=0.0,
                    cov_x=None if cov is None else np.asarray(cov).tolist())


# ------------------------------------------------------------------ model averaging, no fit

def _curve(theta, sd, t=(0.1, 1.0)):
    """A creep curve with ln(J(t) - J0) = theta and its band's sd (the delta method's) on t."""
    t = np.asarray(t, dtype=float)
    theta, sd = np.broadcast_to(theta, t.shape).astype(float), np.broadcast_to(sd, t.shape).astype(float)
    return CreepCurve(t, np.exp(theta), np.exp(theta - Z95 * sd), np.exp(theta + Z95 * sd))


def test_the_averaged_creep_is_the_model_that_holds_all_the_weight():
    one, other = _curve(-20.0, 0.05), _curve(-19.0, 0.01)
    avg = averaged_creep([(1.0, one), (0.0, other)])
    assert np.allclose(avg.J_per_pa, one.J_per_pa, rtol=1e-12) and np.allclose(avg.upper, one.upper, rtol=1e-12)
    # a model without a band (no covariance) is not averaged; the weights are renormalised over the rest
    none = CreepCurve(one.t_s, one.J_per_pa * 3, np.full(2, np.nan), np.full(2, np.nan))
    assert np.allclose(averaged_creep([(0.5, one), (0.5, none)]).lower, one.lower, rtol=1e-12)
    assert not averaged_creep([(1.0, none)]).has_band


def test_the_averaged_band_holds_the_models_spread():
    """Burnham & Anderson's unconditional standard error on ln(J(t) - J0): sum_m w_m sqrt(var_m + (theta_m -
    theta_avg)^2). Two models of equal weight whose own bands do not overlap: the average lies between them and
    its band holds both curves."""
    lo, hi = _curve(-20.0, 0.02), _curve(-19.0, 0.02)
    avg = averaged_creep([(0.3, lo), (0.3, hi)])  # (weights renormalised: 0.5 each)
    se = 0.5 * np.sqrt(0.02**2 + 0.5**2) * 2
    assert np.allclose(np.log(avg.J_per_pa), -19.5) and np.allclose(np.log(avg.upper), -19.5 + Z95 * se)
    assert np.all(avg.lower < lo.J_per_pa) and np.all(hi.J_per_pa < avg.upper)
    assert np.all(lo.upper < hi.lower)  # (neither model's own band holds the other's curve)


# ------------------------------------------------------------------ the delta method, no fit

@pytest.mark.parametrize("tau_free", [True, False])
def test_the_gradient_is_the_derivative_of_ln_creep_in_the_optimisers_variables(tau_free):
    rig = load_rig("perugia")
    c, a = creep_const(rig), 353.73
    J = np.array([2.2e-10, 2.2e-11, 2.2e-12])
    tau = np.array([2.0, 0.2, 0.02])
    t = np.array([0.014, 0.05, 0.5, 5.0, 20.0])
    # x as the optimiser has it: J_k = J'_k / (c a^2)
    x = np.concatenate([[math.log(a)], np.log(J * c * a * a)] + ([np.log(tau)] if tau_free else []))

    def ln_creep(x):
        a_, Jr = math.exp(x[0]), np.exp(x[1:4])
        return np.log(retarded_compliance(Jr / (c * a_ * a_), np.exp(x[4:]) if tau_free else tau, t))

    G, g = log_creep_gradient(J, tau, t, tau_free)
    assert np.allclose(G, retarded_compliance(J, tau, t), rtol=1e-14)
    h = 1e-6
    fd = np.array([(ln_creep(x + h * e) - ln_creep(x - h * e)) / (2 * h) for e in np.eye(x.size)]).T
    assert g.shape == fd.shape
    assert np.allclose(g, fd, atol=1e-7), np.abs(g - fd).max()


def test_the_band_is_the_delta_method_and_agrees_with_sampling_x():
    J = np.array([2.2e-10, 2.2e-11, 2.2e-12])
    tau = np.array([2.0, 0.2, 0.02])
    rng = np.random.default_rng(5)
    A = rng.normal(size=(7, 7))
    cov = 2.5e-4 * (A @ A.T + 7 * np.eye(7))  # about 6 % on each parameter, correlated
    fit = _fit_of(J, tau, cov=cov)
    t = np.array(CHECK_TIMES)
    cc = creep_curve(fit, t)
    G, g = log_creep_gradient(J, tau, t)
    sd = np.sqrt(np.einsum("ij,jk,ik->i", g, cov, g))
    assert np.allclose(cc.lower, G * np.exp(-Z95 * sd)) and np.allclose(cc.upper, G * np.exp(Z95 * sd))
    # the linearisation holds at this size: sampled x give the same 2.5/97.5 % quantiles of ln J(t)
    x0 = np.concatenate([[math.log(353.73)], np.log(J), np.log(tau)])  # c a^2 = 1: only differences matter
    xs = rng.multivariate_normal(x0, cov, 20000)
    lnG = np.log([retarded_compliance(np.exp(x[1:4]) / math.exp(2 * (x[0] - x0[0])), np.exp(x[4:]), t) for x in xs])
    q = np.quantile(lnG, [0.025, 0.975], axis=0)
    # (within 5 % of the half-width: sampling error ~1 %, the curvature of ln J(t) ~1 % at this size)
    assert np.all(np.abs(q[0] - np.log(cc.lower)) < 0.05 * Z95 * sd), (q, np.log(cc.lower))
    assert np.all(np.abs(q[1] - np.log(cc.upper)) < 0.05 * Z95 * sd), (q, np.log(cc.upper))


def test_fixed_parameters_add_no_variance_and_no_covariance_means_no_band():
    J, tau = np.array([1e-10, 1e-11]), np.array([1.0, 0.05])
    cov = np.diag([1e-4, 1e-2, 1e-2, 1e-2, 1e-2])
    fixed = cov.copy()
    fixed[4, :] = fixed[:, 4] = np.nan  # tau_2 on its bound: held fixed
    zeroed = cov.copy()
    zeroed[4, 4] = 0.0
    t = [0.02, 0.2, 2.0]
    assert np.allclose(creep_curve(_fit_of(J, tau, cov=fixed), t).upper, creep_curve(_fit_of(J, tau, cov=zeroed), t).upper)
    assert creep_curve(_fit_of(J, tau, cov=fixed), t).upper[0] < creep_curve(_fit_of(J, tau, cov=cov), t).upper[0]
    for c in (creep_curve(_fit_of(J, tau), t), creep_curve(_fit_of(J, tau, cov=np.full((5, 5), np.nan)), t)):
        assert not c.has_band and np.all(np.isnan(c.lower)) and np.allclose(c.J_per_pa, retarded_compliance(J, tau, t))
    # EL: no creep
    el = _fit_of([], [])
    assert creep_curve(el, t_min_s=0.01, t_max_s=20.0).t_s.size == 0
    # the default range: log-spaced from the lower bound to the window
    cc = creep_curve(_fit_of(J, tau, cov=cov), t_min_s=0.0137, t_max_s=20.0)
    assert cc.t_s.size == CREEP_POINTS and cc.t_s[0] == pytest.approx(0.0137) and cc.t_s[-1] == pytest.approx(20.0)
    assert decades(0.0137, 20.0) == [0.1, 1.0, 10.0] and decades(0.002, 20.0) == [0.01, 0.1, 1.0, 10.0]


# ------------------------------------------------------------------ on data the fitter did not make

@pytest.fixture(scope="module")
def record():
    """(rig, t, clean head) of material A on the reference rig: MOC, quadratic friction, butterfly valve."""
    rig = load_rig("perugia").with_changes(valve=Valve())
    A = load_material("A")
    a = A.wave_speed_m_s
    J_rel = creep_scale(rig, a) * np.array([e.J_per_pa for e in A.elements])
    tau = np.array([e.tau_s for e in A.elements])
    t = np.arange(-1000, 20000) / 1000.0
    m = rig.manoeuvre
    h = moc_head(rig, a, J_rel, tau, t, position=lambda x: commanded_position_pct(x, m.beta_per_s, m.gamma))
    return rig, A, t, rig.steady_head_m + h


_FITS: dict = {}


def fitted(record, seed, sigma=SIGMA, models=None, position=True):
    """The fit of the record with noise ``sigma`` (seed), from the recorded valve position or the head alone."""
    key = (seed, sigma, models, position)
    if key not in _FITS:
        rig, _, t, h = record
        noisy = h + sigma * np.random.default_rng(seed).standard_normal(t.size)
        opts = {} if models is None else {"models": list(models)}
        if position:  # the actuator's feedback, a little noisy
            m = rig.manoeuvre
            opts["position_pct"] = (commanded_position_pct(t, m.beta_per_s, m.gamma)
                                    + np.random.default_rng(seed + 1000).normal(0.0, 0.02, t.size))
        _FITS[key] = fit_record(t, noisy, 0.0, rig, 20.0, record_rate_hz=1000.0, **opts)
    return _FITS[key]


def _check_truth_in_band(record, r, widths=(0.02, 0.02, 0.25)):
    _, A, _, _ = record
    best = r.best
    t = np.array(CHECK_TIMES)
    c = r.creep(best, t)
    truth = A.creep_compliance(t)
    assert c.has_band, best.cov_x
    detail = (f"{best.name}: truth {truth}, fit {c.J_per_pa}, band {c.lower} .. {c.upper}\n"
              + format_report(r, elements=True))
    assert np.all(c.lower <= truth) and np.all(truth <= c.upper), detail
    # a band, not a blanket: under 1 % at 0.05 and 0.5 s, some 15 % at 5 s (the slow element's tau,
    # 2 s, against a 20 s window in which the head has died down)
    assert np.all(np.log(c.upper / c.J_per_pa) < widths), detail


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_the_true_creep_of_material_A_lies_in_the_best_models_band(record, seed):
    r = fitted(record, seed)
    assert r.best.name == "S3", format_report(r, elements=False)
    _check_truth_in_band(record, r)


@pytest.mark.parametrize("seed", [11, 12])
def test_from_the_head_alone_the_band_carries_the_closures_uncertainty(record, seed):
    """Head only: the closure's shape is fitted from the same record and trades with the slow element
    (J(5 s) 20-60 % high before the covariance was marginalised over it, outside a band of 16-21 %);
    with the closure's parameters in the covariance (velab.fitting.nuisance) the truth lies in a band
    that is wider at 5 s (measured 26 %), not a blanket."""
    _check_truth_in_band(record, fitted(record, seed, models=(3,), position=False), widths=(0.02, 0.02, 0.4))


def test_the_band_narrows_as_the_noise_falls(record):
    wide = fitted(record, 11, SIGMA, models=(3,))
    narrow = fitted(record, 11, SIGMA / 4, models=(3,))
    t = np.array(CHECK_TIMES)
    w_wide = np.log(wide.creep(wide["S3"], t).upper / wide.creep(wide["S3"], t).lower)
    w_narrow = np.log(narrow.creep(narrow["S3"], t).upper / narrow.creep(narrow["S3"], t).lower)
    # the band scales with the noise (0.25 here: the fit's sigma over four); measured 0.24-0.25
    assert np.all((0.15 < w_narrow / w_wide) & (w_narrow / w_wide < 0.4)), (w_narrow, w_wide)


def test_json_and_the_run_file_keep_the_band(record, tmp_path):
    r = fitted(record, 11)
    d = r.to_dict()
    lo, hi = creep_range(r)
    for f, md in zip(r.models, d["models"]):
        creep = md["creep"]
        assert set(creep) == {"t_s", "J_per_pa", "lower", "upper"}
        if f.m == 0:
            assert creep["t_s"] == [] and creep["J_per_pa"] == []
            continue
        assert len(creep["t_s"]) == CREEP_POINTS and creep["t_s"][0] == pytest.approx(lo)
        assert creep["t_s"][-1] == pytest.approx(hi) and hi == r.window_s
        assert np.all(np.asarray(creep["lower"]) < creep["J_per_pa"])
    # the model-averaged creep: over the models that have a band, weights (vanished-element twins merged) summing
    # to 1; on this record S3 (the truth) holds most and S4 the rest: the average within S3's band, its band wider
    avg = d["creep_averaged"]
    assert set(avg) == {"t_s", "J_per_pa", "lower", "upper", "weights", "weight_left_out"}
    assert sum(avg["weights"].values()) == pytest.approx(1.0) and avg["weights"][r.best.name] > 0.5
    own = d["models"][r.models.index(r.best)]["creep"]
    assert np.all(np.asarray(own["lower"]) < avg["J_per_pa"]) and np.all(np.asarray(avg["J_per_pa"]) < own["upper"])
    assert np.all(np.asarray(avg["upper"]) - avg["lower"] >= 0.999 * (np.asarray(own["upper"]) - own["lower"]))
    # strict JSON (velab fit --json: NaN -> null, the fixed parameters' rows) and back
    back = SweepResult.from_dict(json.loads(json.dumps(json_ready(d), allow_nan=False)))
    best, best_back = r.best, back[r.best.name]
    assert best_back.cov_x is not None
    assert np.array_equal(np.isnan(best.cov_x), np.isnan(best_back.cov_x))
    ref = r.creep(best)
    got = back.creep(best_back)
    assert np.allclose(got.J_per_pa, ref.J_per_pa, rtol=1e-12) and np.allclose(got.upper, ref.upper, rtol=1e-12)
    # the run file
    with h5py.File(tmp_path / "fits.h5", "w") as fh:
        write_fit_group(fh, "creep", r)
    with h5py.File(tmp_path / "fits.h5", "r") as fh:
        stored = read_fit_group(fh["creep"])
        assert np.allclose(fh["creep"][best.name]["creep"]["upper"][()], ref.upper)
    got = stored.creep(stored[best.name])
    assert got.has_band and np.allclose(got.lower, ref.lower, rtol=1e-12) and np.allclose(got.upper, ref.upper)
    assert np.allclose(stored.creep_averaged().curve.upper, r.creep_averaged().curve.upper, rtol=1e-12)


def test_a_fit_stored_before_the_covariance_reads_with_no_band(record):
    r = fitted(record, 11)
    d = r.to_dict()
    for md in d["models"]:
        del md["cov_x"], md["creep"]
    old = SweepResult.from_dict(d)
    assert all(f.cov_x is None for f in old.models)
    c = old.creep()
    assert not c.has_band and np.allclose(c.J_per_pa, r.creep().J_per_pa)
    assert all(v is None for v in json.loads(json.dumps(json_ready(old.to_dict())))["models"][3]["creep"]["lower"])
    assert "no band (the fit holds no covariance)" in format_report(old)
    # a damaged covariance (not the model's size) is no covariance either
    d["models"][3]["cov_x"] = [[1.0, 0.0], [0.0, 1.0]]
    assert SweepResult.from_dict(d).models[3].cov_x is None


def test_the_report_gives_the_best_models_creep_at_the_decades(record):
    r = fitted(record, 11)
    lines = creep_lines(r)
    best = r.best
    assert lines[0].startswith(f"creep of {best.name}: J(t) - J0 (1/Pa), 95 % band")
    times = decades(*creep_range(r))
    assert times == [0.1, 1.0, 10.0]  # tau_min 13.7 ms on this rig, window 20 s
    c = r.creep(best, times)
    for line, t, J, lo, hi in zip(lines[1:], times, c.J_per_pa, c.lower, c.upper):
        assert line == f"  t = {t:g} s: {J:.3e}  [{lo:.3e}, {hi:.3e}]"
    # S4 holds a share of the Akaike weight here (S3 0.84): the model-averaged creep follows, its band the models'
    avg = r.creep_averaged(times)
    assert 0.5 < avg.weights[best.name] < 0.99 and len(lines) == 2 * (1 + len(times))
    assert lines[1 + len(times)].startswith(f"model-averaged creep (Akaike weights {best.name} "
                                            f"{avg.weights[best.name]:.2f}")
    for line, t, J, lo, hi in zip(lines[2 + len(times):], times, avg.curve.J_per_pa, avg.curve.lower, avg.curve.upper):
        assert line == f"  t = {t:g} s: {J:.3e}  [{lo:.3e}, {hi:.3e}]"
    text = format_report(r)
    assert "\n".join(lines) in text
    # an elastic best model creeps not at all
    el = SweepResult.from_dict({**r.to_dict(), "models": [r.to_dict()["models"][0]]})
    assert creep_lines(el) == ["creep of EL: none (an elastic wall: J(t) = J0)"]


def test_the_figure_hatches_the_model_averaged_band_where_the_choice_is_uncertain(record):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from velab.fitting.plots import averaged_band

    r = fitted(record, 11)  # S3 0.84, S4 0.16
    fig, ax = plt.subplots()
    try:
        art = averaged_band(ax, r)
        assert art is not None and art.get_label() == "model-averaged 95 % band"
        box = art.get_paths()[0].get_extents()
        c = r.creep_averaged().curve
        assert box.y0 == pytest.approx(c.lower.min()) and box.y1 == pytest.approx(c.upper.max())
        # one model holding the weight: nothing drawn
        one = SweepResult.from_dict({**r.to_dict(), "models": [m for m in r.to_dict()["models"] if m["name"] == "S3"]})
        one.models[0].weight = 1.0
        assert averaged_band(ax, one) is None
    finally:
        plt.close(fig)
