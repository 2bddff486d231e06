"""The manoeuvre in the fit (velab.fitting.manoeuvre): the flow at the valve built from the record.

Science on data the fitting model did not make: the time-domain model (MOC, quadratic friction) with
the orifice law at the valve (velab.moc, position -> rig.valve), two rigs, truths EL..S3 (S4 on the
imperial rig), several valve characteristics and loss shares, white noise 0.1 m; the head-only path
(a closure fitted as nuisance parameters) and the recorded-position path.
"""

import json
import math

import numpy as np
import pytest

from velab.cli import main
from velab.config import load_material, load_rig
from velab.errors import DataError
from velab.fitting.closure import (closure_opening, from_solver, half_flow_offset, own_valve_starts, tail_shape,
                                   to_solver)
from velab.fitting.flows import (ValveInput, closing_position, closure_flow, coupling_head, early_window_s,
                                 position_flow, result_flow)
from velab.fitting.manoeuvre import valve_input
from velab.fitting.params import FitBounds
from velab.fitting.entry import fit_record
from velab.fitting.prepare import prepare_record
from velab.fitting.refine import refine_closure
from velab.fitting.sweep import SweepContext, fit_sweep
from velab.model import ValveHeadModel, flow_perturbation
from velab.moc import moc_head
from velab.valvelaw import Valve, commanded_position_pct
from velab.fitting.report import format_report

SIGMA = 0.1
# truth -> (J'_k, tau_k / T), T = 4L/a (as tests/fitting/test_fit_truths.py)
TRUTHS = {
    "EL": ((), ()),
    "S1": ((0.1,), (0.43,)),
    "S2": ((0.03, 0.15), (0.043, 1.3)),
    "S3": ((0.0041, 0.041, 0.41), (0.01724, 0.1724, 1.724)),
    "S4": ((0.01, 0.03, 0.1, 0.3), (0.01724, 0.069, 0.30, 1.29)),
}
# a manufacturer-like table: a power law near 1.9 with a linear last tenth of the stroke
TABLE = Valve(characteristic="table", series_loss_share=0.02, position_pct=(0, 10, 20, 30, 40, 50, 60, 70, 80, 90, 100),
              flow_ratio=(0, 0.015, 0.05, 0.11, 0.19, 0.29, 0.42, 0.57, 0.74, 0.9, 1.0))
VALVES = {
    "butterfly": Valve(),
    "power1.5": Valve(characteristic="power", exponent=1.5, series_loss_share=0.1),
    "table": TABLE,
    "linear": Valve(characteristic="linear", series_loss_share=0.2),
    "quick": Valve(characteristic="quick-opening", series_loss_share=0.05),
}


def valve_record(rig, truth, valve, seed=11, pre=1.0, seconds=20.0):
    """(rig with that valve, t on the run's axis with the trigger at 0, absolute head): the MOC with the
    orifice law, the actuator on the rig's sigmoid in position."""
    rig = rig.with_changes(valve=valve)
    J, rel = TRUTHS[truth]
    a = rig.nominal_wave_speed_m_s
    period = 4 * rig.pipe.length_m / a
    t = np.arange(-int(pre * 1000), int(seconds * 1000)) / 1000.0
    m = rig.manoeuvre
    h = moc_head(rig, a, np.array(J, dtype=float), np.array(rel, dtype=float) * period, t,
                 position=lambda x: commanded_position_pct(x, m.beta_per_s, m.gamma))
    return rig, t, rig.steady_head_m + h + np.random.default_rng(seed).normal(0.0, SIGMA, t.size)


# ------------------------------------------------------------------ the closure family

def test_the_closure_family_holds_the_papers_sigmoid_and_a_butterfly_exactly():
    rig = load_rig("perugia")
    m = rig.manoeuvre
    t = np.linspace(0.0, 0.6, 601)
    # the paper's imposed flow: n = 1, s = 1, no coupling
    assert np.allclose(closure_opening(t, m.beta_per_s, m.half_closure_s, 1.0, 1.0),
                       1.0 / (1.0 + np.exp(m.beta_per_s * t + m.gamma)), atol=1e-12)
    # a butterfly (p/100)^2 with a 5 % loss share, driven along the commanded sigmoid in position
    assert np.allclose(closure_opening(t, m.beta_per_s, m.half_closure_s, 2.0, 0.05),
                       Valve().opening(commanded_position_pct(t, m.beta_per_s, m.gamma)), atol=1e-12)
    # and open before the trigger
    assert closure_opening(np.array([-0.1]), 32.0, 0.17, 2.0, 0.05)[0] == 1.0


@pytest.mark.parametrize("valve", [(32.0, 0.17, 2.0, 0.05, 1.0, 0.0), (40.0, 0.12, 1.0, 1.0, 0.0, 0.0),
                                   (28.0, 0.2, 2.5, 0.03, 0.5, 0.3)])
def test_the_solver_variables_anchor_the_flows_half_closure(valve):
    v = to_solver(valve)
    assert np.allclose(from_solver(v), valve, atol=1e-12)
    # the solver's t50 is where the effective opening is 1/2
    beta, t_half, power, share, _, tail = valve
    assert closure_opening(np.array([v[1]]), beta, t_half, power, share, tail)[0] == pytest.approx(0.5, abs=1e-9)
    assert half_flow_offset(1.0, 1.0) == pytest.approx(0.0, abs=1e-12)  # the sigmoid is half shut at t_half


def test_a_new_flow_drives_the_model_as_a_model_built_on_it():
    rig = load_rig("perugia")
    t = np.arange(-50, 4000) / 1000.0
    q = closure_flow(t, np.zeros_like(t), rig, (32.0, 0.17, 2.0, 0.05, 1.0, 0.0))
    vm = ValveHeadModel(rig, t, band_hz=None)  # built on the rig's sigmoid
    J, tau = np.array([0.04, 0.4]), np.array([0.2, 2.0])
    direct = ValveHeadModel(rig, t, band_hz=None, flow=q).head_params(353.0, J, tau)
    assert np.allclose(vm.head_of(vm.impedance(353.0, J, tau), vm.flow_sums(q)), direct, atol=1e-9)


def test_the_manoeuvre_input_modes():
    rig = load_rig("perugia")
    t = np.arange(0, 3000) / 1000.0
    d = np.zeros_like(t)
    vi = valve_input(t, d, rig, 3.0, mode="rig")
    assert vi.source == "rig" and vi.k == 0 and np.array_equal(vi.flow, flow_perturbation(t, rig))
    pos = commanded_position_pct(t, 32.0, -5.5)
    vi = valve_input(t, d, rig, 3.0, position_pct=pos)
    assert vi.source == "position" and vi.k == 0
    stroke = closing_position(t, pos, rig)  # low-passed, never reopening
    assert np.all(np.diff(stroke) <= 0) and np.allclose(stroke, pos, atol=0.05)
    assert np.allclose(vi.flow, rig.steady_flow_m3_s * (rig.valve.opening(stroke) - 1.0))  # no head rise: no coupling
    imposed = rig.with_changes(valve=Valve(law="imposed", characteristic="linear"))
    assert np.allclose(valve_input(t, d, imposed, 3.0, position_pct=pos).flow,
                       rig.steady_flow_m3_s * (stroke / 100 - 1))
    # feedback noise near shut does not open a shut valve again
    noisy = pos + np.random.default_rng(1).normal(0.0, 0.05, t.size)
    assert closing_position(t, noisy, rig)[-1000:].max() < 0.02
    with pytest.raises(DataError, match="unknown manoeuvre input"):
        valve_input(t, d, rig, 3.0, mode="sigmoid")
    # a stored fit's flow is rebuilt from its settings (figures); older fits have none
    assert result_flow({}, t, d, rig) is None
    fitted = ValveInput("fitted", np.zeros_like(t), dict(beta_per_s=32.0, t_half_s=0.17, power=2.0, loss_share=0.05,
                                                       coupling=1.0, tail=0.0))
    assert np.allclose(result_flow({"manoeuvre": fitted.describe()}, t, d, rig),
                       closure_flow(t, d, rig, (32.0, 0.17, 2.0, 0.05, 1.0, 0.0)))


def test_a_rigs_table_is_the_closure_familys_blended_shape():
    """A rig whose valve has a characteristic table: the family phi = (1 - w) x^n + w g(x) takes the table as g,
    so at w = 1 it is the rig's valve on its sigmoid exactly (and the fit starts there); other rigs blend a line."""
    rig = load_rig("perugia").with_changes(valve=TABLE)
    m = rig.manoeuvre
    t = np.linspace(0.0, 0.6, 601)
    shape = tail_shape(rig)
    assert shape is not None and tail_shape(load_rig("perugia")) is None
    (start,) = own_valve_starts(rig)
    beta, t_half, power, share, kappa, tail = start
    assert (beta, t_half, share, kappa, tail) == (m.beta_per_s, m.half_closure_s, TABLE.series_loss_share, 1.0, 1.0)
    assert np.allclose(closure_opening(t, beta, t_half, power, share, tail, shape),
                       TABLE.opening(commanded_position_pct(t, m.beta_per_s, m.gamma)), atol=1e-12)
    assert own_valve_starts(load_rig("perugia")) == []


# ------------------------------------------------------------------ science

@pytest.mark.parametrize("rig_name,truth,valve", [
    ("perugia", "S3", "butterfly"),
    ("perugia", "S1", "power1.5"),
    ("imperial", "S2", "table"),
    # the table in the rig file is the closure family's blended shape: the valve is described exactly (before:
    # a power law with a linear tail, S1 named at F/noise 1.08)
    ("perugia", "EL", "table"),
    ("imperial", "EL", "linear"),
    ("imperial", "S3", "power1.5"),
    ("imperial", "S1", "quick"),
    # a valve that shuts abruptly and a fast element smooth the fronts alike: the lead's closure, refined with
    # its S2 wall, took the element up; the continuation searches again and the closure is refined with the
    # wall of the model it names (below, test_a_quick_valve_head_only_record_names_s3_with_margin_...)
    ("perugia", "S3", "quick"),
])
def test_a_real_valve_head_only_record_names_the_truth(rig_name, truth, valve):
    """No position in the record: the closure is fitted with the wall. The true model, its wave speed
    (within 1 m/s and within its stated uncertainty), residuals at the record's noise, no warning."""
    rig, t, h = valve_record(load_rig(rig_name), truth, VALVES[valve])
    r = fit_record(t, h, 0.0, rig, 20.0, record_rate_hz=1000.0)
    b = r.best
    # five: the coupling exponent is the rig's valve law's (the orifice law: 1), not fitted; two when the shape is
    # held at the rig's valve (manoeuvre.choose_closure: the rig file describes the valve that made the record)
    man = r.settings["manoeuvre"]
    assert man["source"] == "fitted" and man["nuisance_parameters"] == (2 if man["shape"] == "rig" else 5), man
    assert r.settings["manoeuvre"]["params"]["coupling"] == 1.0
    assert b.name == truth, format_report(r, elements=False)
    a_true = rig.nominal_wave_speed_m_s
    assert abs(b.wave_speed_m_s - a_true) <= 1.0
    # the stated standard error holds (the MOC's own discretisation allows a few cm/s)
    assert abs(b.wave_speed_m_s - a_true) <= max(4 * b.wave_speed_se_m_s, 0.05), (b.wave_speed_m_s, b.wave_speed_se_m_s)
    assert b.noise_ratio <= 1.1
    assert not [w for w in r.warnings if w["code"] == "misfit"]


def test_the_first_parts_closure_of_a_late_closing_valve_follows_its_flow():
    """A quick-opening valve passes its flow until late in the stroke (half of it at 0.30 s, where the rig's
    sigmoid says 0.17 s). The first part's wave-speed scan drives an elastic pipe with the rig's sigmoid: it
    came out at 237 m/s for 353.7, the first part's fit was boxed around it, its closure missed the flow by
    6 % of Q0 rms (F 90 x the noise there) and every later stage started from that. The box holds the rig's
    nominal wave speed too."""
    rig, t, h = valve_record(load_rig("perugia"), "S3", VALVES["quick"])
    rec = prepare_record(t, h, 0.0, rig, 20.0, record_rate_hz=1000.0)
    vi = valve_input(rec.t, rec.h, rig, rec.window_s)
    m = rig.manoeuvre
    true = position_flow(rec.t, coupling_head(rec.t, rec.h, rig), commanded_position_pct(rec.t, m.beta_per_s, m.gamma),
                         rig)
    ne = int(np.searchsorted(rec.t, early_window_s(rig, rec.window_s)))
    assert np.sqrt(np.mean((vi.flow[:ne] - true[:ne]) ** 2)) < 0.03 * rig.steady_flow_m3_s


@pytest.mark.parametrize("made, described", [("butterfly", "butterfly"), ("quick", "quick"), ("table", "table"),
                                             ("quick", "butterfly"), ("butterfly", "linear"), ("table", "butterfly")])
def test_the_closures_shape_is_the_rigs_valve_unless_the_record_shows_another(made, described):
    """``shape="auto"`` (every fit's head-only closure): the closure fitted on the first part with its shape held
    at the valve the rig file describes, and free where the held fit's score says freeing it may pay; the rig's
    taken unless the free one gains more than SHAPE_PRICE (11.34, chi2(3)'s 1 % point). A record made by the
    valve its rig describes keeps that shape (only the timing fitted, 3 fewer nuisance parameters) but for a
    chance gain (seeds 11-16 x three valves, 29 campaign records: scores 0-11, fitted gains -0.02..10); a record
    of a valve clearly not the one described gets its shape fitted (gains 114-293 on these)."""
    from velab.fitting.closure import FITTED, rig_shape
    from velab.fitting.closurefit import SHAPE_PARAMS, SHAPE_PRICE

    rig, t, h = valve_record(load_rig("perugia"), "S3", VALVES[made], seconds=8.0)
    rig = rig.with_changes(valve=VALVES[described])
    rec = prepare_record(t, h, 0.0, rig, 8.0, record_rate_hz=1000.0)
    vi = valve_input(rec.t, rec.h, rig, rec.window_s, shape="auto")
    shape = vi.shape
    assert vi.source == "fitted" and vi.shape_gain == pytest.approx(vi.describe()["shape_gain"])
    if made == described:
        assert shape == "rig" or vi.shape_gain < 20.0, vi.text
    else:
        assert shape == "fitted" and vi.shape_gain > 50.0, vi.text
    assert (shape == "rig") == (vi.shape_gain <= SHAPE_PRICE)
    assert vi.k == FITTED - (SHAPE_PARAMS if shape == "rig" else 0)
    assert vi.describe()["shape"] == shape and vi.describe()["nuisance_parameters"] == vi.k
    power, share, tail = rig_shape(rig)
    if shape == "rig":
        assert (vi.params["power"], vi.params["loss_share"], vi.params["tail"]) == pytest.approx((power, share, tail))
        assert "held at the rig's valve" in vi.text
    else:
        assert "its shape fitted" in vi.text
    # the flow it drives the model with is the record's: within 3 % of Q0 rms of the true one on the first part
    m = rig.manoeuvre
    true = position_flow(rec.t, coupling_head(rec.t, rec.h, rig.with_changes(valve=VALVES[made])),
                         commanded_position_pct(rec.t, m.beta_per_s, m.gamma), rig.with_changes(valve=VALVES[made]))
    ne = int(np.searchsorted(rec.t, early_window_s(rig, rec.window_s)))
    assert np.sqrt(np.mean((vi.flow[:ne] - true[:ne]) ** 2)) < 0.03 * rig.steady_flow_m3_s


@pytest.mark.parametrize("made, described", [("butterfly", "butterfly"), ("quick", "butterfly")])
def test_the_shape_score_predicts_what_the_free_shape_gains(made, described):
    """``shape_score`` (the gain a Gauss-Newton step from the held closure predicts for a free shape) decides
    whether the free fit is made at all: it must not hide a gain the fit would find. On a valve as described,
    both small and within a few units; on a valve not the one described, both far above the price."""
    from velab.fitting.friction import TimeDomainModel
    from velab.fitting.closurefit import SHAPE_PRICE, EarlyPart, fit_early, shape_score

    rig, t, h = valve_record(load_rig("perugia"), "S3", VALVES[made], seconds=8.0)
    rig = rig.with_changes(valve=VALVES[described])
    rec = prepare_record(t, h, 0.0, rig, 8.0, record_rate_hz=1000.0)
    early = EarlyPart(rec.t, rec.h, rig, rec.window_s, TimeDomainModel(rig, rec.t))
    held, x_held = fit_early(early, "rig")
    score = shape_score(early, x_held)
    free, _ = fit_early(early, "fitted", extra_starts=(x_held,))
    gain = free.early_n * math.log(held.early_F / free.early_F)
    assert gain >= -1e-6  # (the held optimum is a start of the free fit: its family contains it)
    if made == described:
        assert score < SHAPE_PRICE and abs(score - gain) < 4.0, (score, gain)
    else:
        assert score > 5 * SHAPE_PRICE and gain > 5 * SHAPE_PRICE, (score, gain)
    # no prediction at a point where the model is not finite: the free fit is made (the score is infinite)
    with np.errstate(invalid="ignore", divide="ignore"):
        assert shape_score(early, np.full_like(x_held, np.nan)) == math.inf


def test_a_closure_whose_fronts_come_late_is_still_found_with_the_rigs_shape():
    """The imperial rig (277 m, creep delaying the fronts) at 1.25 x its Q0: the wave speed scanned from the first
    part with the rig's sigmoid imposed as the flow was 359.5 m/s for 395, and the closure fit with the rig's
    shape stopped there (F 18 x the noise's, beta 43.4 for 40); a free shape then made up for it (a gain of
    3900). Scanned with the rig's own valve on its sigmoid, the held fit reaches the record's closure."""
    from velab.model import creep_scale

    base = load_rig("imperial")
    rig = base.with_changes(steady_flow_m3_s=1.25 * base.steady_flow_m3_s)
    A = load_material("A")
    a = base.nominal_wave_speed_m_s
    J = creep_scale(rig, a) * np.array([e.J_per_pa for e in A.elements[:2]])
    tau = np.array([e.tau_s for e in A.elements[:2]])
    t = np.arange(-1000, 20000) / 1000.0  # (the whole window: its time-domain model is the closure fit's too)
    m = rig.manoeuvre
    h = rig.steady_head_m + moc_head(rig, a, J, tau, t, position=lambda x: commanded_position_pct(x, m.beta_per_s, m.gamma))
    h = h + np.random.default_rng(7).normal(0.0, 0.1, t.size)
    rec = prepare_record(t, h, 0.0, rig, 20.0, record_rate_hz=1000.0)
    vi = valve_input(rec.t, rec.h, rig, rec.window_s, shape="auto")
    assert vi.shape == "rig", vi.text
    assert vi.params["beta_per_s"] == pytest.approx(m.beta_per_s, abs=1.5)
    assert vi.early_F < 1.1 * 0.1**2  # the noise's variance: the closure is the record's


def test_a_quick_valve_head_only_record_names_s3_with_margin_and_its_own_closure():
    """The knife edge (tests above: S2 named on one machine, S3 on another): a fast element (17 ms) smooths the
    fronts as an abrupt closure does. The record changed far below its noise (1e-9 m: any change of its last bits
    sends the solvers down other paths, as another CPU's rounding does; the record itself is the
    [perugia-S3-quick] case above) names S3 with S2 more than 100 AIC units behind (207-278 on eight such
    changes and other noise seeds) and wave speeds within two standard errors of each other. Change 8 ended in a
    closure at the box's corner (power 6, loss share 0.001) that its fast element made up for, S2 only 42 behind
    and 170 in n ln F short of the quick-opening optimum, until the refinement got a quick-opening prototype
    (velab.fitting.refine.PROTOTYPES).

    And the closure is the named model's: refined again with its wall and every model continued, S3 gains less
    than 8 in n ln F and its wave speed moves by less than 1.5 of its standard error. A closure refined with
    another model's wall was 34-290 short (seeds 12 and 14 before the closure was refined with the named model's
    wall); the fit path itself ends near, not at, that fixed point: the refinement and the continuation
    alternated converge slowly (docs/fitting.md), measured 0-5.8 in n ln F and up to 1.07 standard errors on
    eight records of this valve (noise seeds and changes), up to 3.8 and 0.48 on the five records of
    benchmarks/fit_joint.py (a round that took the fit to the fixed point cost a continuation, ~2 s, per round
    and did not converge on that campaign's first record: not taken)."""
    rig, t, h = valve_record(load_rig("perugia"), "S3", VALVES["quick"])
    a = []
    for seed in (8, 5):
        x = h + 1e-9 * np.random.default_rng(seed).normal(size=h.size)
        r = fit_record(t, x, 0.0, rig, 20.0, record_rate_hz=1000.0)
        assert r.best.name == "S3", format_report(r, elements=False)
        assert r["S2"].delta_aic > 100, (seed, r["S2"].delta_aic)
        assert r.settings["manoeuvre"]["refined_with"] == "S3"
        a.append((r.best.wave_speed_m_s, r.best.wave_speed_se_m_s))
        rec = prepare_record(t, x, 0.0, rig, 20.0, record_rate_hz=1000.0)
        vi = valve_input(rec.t, rec.h, rig, rec.window_s, closure=r.settings["manoeuvre"])
        again = refine_closure(rec.t, rec.h, rig, vi, r.best, FitBounds.from_dict(r.settings["bounds"]))
        r2 = fit_sweep(rec.t, rec.h, rig, window_s=None, context=SweepContext(flow=again.flow, lead=r, trust_lead=False))
        assert r.n * math.log(r.best.F / r2["S3"].F) < 8.0, seed
        assert abs(r2["S3"].wave_speed_m_s - r.best.wave_speed_m_s) < 1.5 * r.best.wave_speed_se_m_s, seed
    assert abs(a[0][0] - a[1][0]) <= 2 * max(se for _, se in a)


def test_each_model_is_compared_under_its_own_closure():
    """S2 truth, real butterfly, head only (seed 13): under the closure refined with S3's wall S3 came out 6.3
    AIC units ahead of S2; refined with S2's own wall, S2 is named and better than S3 under its own, and the
    fit says so. The wave speed within its standard error, as with the recorded position."""
    rig, t, h = valve_record(load_rig("perugia"), "S2", VALVES["butterfly"], seed=13)
    r = fit_record(t, h, 0.0, rig, 20.0, record_rate_hz=1000.0)
    assert r.best.name == "S2", format_report(r, elements=False)
    assert r.settings["manoeuvre"]["refined_with"] == "S2"
    # (with the closure's shape held at the rig's valve -- manoeuvre.choose_closure -- the lead's closure is
    # refined with S2's wall already; with a fitted shape S3's came first and S2 won under its own: the note)
    assert (r.settings["manoeuvre"]["shape"] == "rig"
            or any("under the closure refined with its own wall" in n for n in r.notes)), r.notes
    assert abs(r.best.wave_speed_m_s - 353.73) <= max(4 * r.best.wave_speed_se_m_s, 0.05)
    assert r.best.noise_ratio <= 1.1 and not r.warnings


def test_the_rigs_sigmoid_as_the_flow_misfits_a_real_valve():
    """What velab did before: the rig's sigmoid imposed as the flow, on a real butterfly's record: the
    wrong model, far above the noise, and now said so."""
    rig, t, h = valve_record(load_rig("perugia"), "S3", VALVES["butterfly"])
    r = fit_record(t, h, 0.0, rig, 20.0, record_rate_hz=1000.0, manoeuvre="rig")
    assert r.best.name != "S3" and r.best.noise_ratio > 10
    assert [w for w in r.warnings if w["code"] == "misfit"]


def test_a_recorded_position_drives_the_fit():
    rig, t, h = valve_record(load_rig("perugia"), "S3", VALVES["butterfly"])
    m = rig.manoeuvre
    pos = commanded_position_pct(t, m.beta_per_s, m.gamma) + np.random.default_rng(2).normal(0, 0.02, t.size)
    r = fit_record(t, h, 0.0, rig, 20.0, record_rate_hz=1000.0, position_pct=pos)
    assert r.settings["manoeuvre"]["source"] == "position" and r.settings["manoeuvre"]["nuisance_parameters"] == 0
    assert r.best.name == "S3" and abs(r.best.wave_speed_m_s - 353.73) <= 1.0 and r.best.noise_ratio <= 1.1
    # a position with a hole in the window is not used: the closure is fitted instead, and said so
    pos[5000] = np.nan
    r2 = fit_record(t, h, 0.0, rig, 20.0, record_rate_hz=1000.0, position_pct=pos, models=[3])
    assert r2.settings["manoeuvre"]["source"] == "fitted"
    assert any("valve position not finite" in n for n in r2.notes)


def test_a_one_step_fit_refines_its_closure_over_the_whole_window():
    """A 6 s window: the sweep, the closure refined with the best wall over the
    whole window, and every model calibrated again under it."""
    rig, t, h = valve_record(load_rig("perugia"), "S1", VALVES["butterfly"], seconds=6.0)
    r = fit_record(t, h, 0.0, rig, 6.0, record_rate_hz=1000.0, models=[0, 1, 2])
    assert "fitted over 6 s with the wall" in r.settings["manoeuvre"]["text"]
    p, se = r.settings["manoeuvre"]["params"], r.settings["manoeuvre"]["se"]
    # the flow's half-closure instant is pinned to within milliseconds
    t50 = to_solver([p[k] for k in ("beta_per_s", "t_half_s", "power", "loss_share", "coupling", "tail")])[1]
    true_t50 = to_solver((32.0, 5.5 / 32.0, 2.0, 0.05, 1.0, 0.0))[1]
    assert abs(t50 - true_t50) < 0.005
    assert all(math.isfinite(v) for v in se.values())
    assert r.best.noise_ratio <= 1.1
    # S1, or S1 plus a slow ramp: an element at the retardation-time bound (10 windows), which only
    # creeps linearly in the window and soaks up the steady head's error (sigma / sqrt(1000) = 3 mm
    # here; docs/fitting.md, "What is left")
    b = r.best
    assert b.name == "S1" or (b.name == "S2" and max(b.tau_s) >= 0.99 * r.settings["bounds"]["tau_max_s"]), \
        format_report(r, elements=True)


def test_acceptance_head_only_csv_of_a_real_valve(tmp_path, capsys):
    """Issue 24: material A on the reference rig, quadratic friction, real butterfly valve driven with the
    rig's sigmoid, sigma 0.1 m, head-only CSV through `velab import` and the default `velab fit`: S3,
    |a - 353.73| <= 1 m/s, noise ratio <= 1.5, no misfit. With the position column: the same, from it."""
    run = tmp_path / "a.h5"
    assert main(["synth", "--material", "A", "-o", str(run)]) == 0
    from velab.runfiles import read_run

    rec = read_run(run)
    assert rec.rig.valve.law == "orifice" and "valve_position" in rec.channels
    csv = tmp_path / "a.csv"
    with open(csv, "w") as f:
        f.write("time_s,head_m,valve_pct\n")
        for a, b, c in zip(rec.time_s, rec.head_m, rec.channels["valve_position"]):
            f.write(f"{a:.6f},{b:.6f},{c:.5f}\n")
    for extra, source in (([], "fitted"), (["--valve-column", "valve_pct"], "position")):
        out = tmp_path / f"imported_{source}.h5"
        assert main(["import", str(csv), "--rig", "perugia", "-o", str(out)] + extra) == 0
        capsys.readouterr()
        assert main(["fit", str(out), "--json", "--no-save"]) == 0
        doc = json.loads(capsys.readouterr().out)
        best = next(m for m in doc["models"] if m["name"] == doc["best"])
        assert doc["best"] == "S3" and abs(best["wave_speed"] - 353.73) <= 1.0 and best["noise_ratio"] <= 1.5
        assert not [w for w in doc["warnings"] if w["code"] == "misfit"]
        assert doc["settings"]["manoeuvre"]["source"] == source


def test_import_names_a_missing_or_bad_valve_column(tmp_path, capsys):
    csv = tmp_path / "r.csv"
    csv.write_text("t,h,p\n" + "".join(f"{i / 1000},{30 + 0.01 * i},{100 if i < 20 else 140}\n" for i in range(40)))
    assert main(["import", str(csv), "--rig", "perugia", "-o", str(tmp_path / "x.h5"), "--valve-column", "q"]) == 2
    assert "no valve position column 'q'" in capsys.readouterr().err
    assert main(["import", str(csv), "--rig", "perugia", "-o", str(tmp_path / "x.h5"), "--valve-column", "p"]) == 2
    err = capsys.readouterr().err
    assert "line 22" in err and "not a percentage open" in err
    assert not (tmp_path / "x.h5").exists()
