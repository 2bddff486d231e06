"""The method-of-characteristics model (velab.moc) and its cross-checks with the frequency model.

The MOC shares no code with the transfer-matrix model except the rig constants and
the imposed q(t), so agreement of the two (with the friction laws both represent
exactly: linear, none, Vardy-Brown, and the imposed valve flow) checks both.
Frequency-model references span 30 s or more, so that their own wrap-around (a few mm
on a 3-5 s record) stays out. The valve's orifice law (physics.md section 10), which
only the MOC carries, is checked at the end: the law itself at every step, its limits,
its convergence in dt (its figures on the reference rig are in tests/test_valvelaw.py).
"""

from __future__ import annotations

import numpy as np
import pytest
from moc_reference import march_reference

from velab.config import KelvinVoigt, Material, load_material, load_rig
from velab.rig import GRAVITY_M_S2
from velab.model import ValveHeadModel, creep_scale, flow_perturbation, valve_head
from velab.moc import commanded_opening, grid, moc_head, moc_solve, moc_transient, moc_valve_head
from velab.moc.solver import run
from velab.synth import with_valve_law
from velab.valvelaw import commanded_position_pct, orifice_flow


@pytest.fixture(scope="module")
def rig():
    # the paper's model: linearised friction, the sigmoid imposed as the valve flow
    return with_valve_law(load_rig("perugia").with_changes(friction="linear"), "imposed")


def _joukowsky(rig, a):
    return a * rig.steady_flow_m3_s / (GRAVITY_M_S2 * rig.pipe.area_m2)


def _params(rig, mat):
    a = mat.wave_speed_m_s
    J = np.array([e.J_per_pa for e in mat.elements]) * creep_scale(rig, a)
    return a, J, np.array([e.tau_s for e in mat.elements])


def _long_reference(rig, mat, dt, n):
    """Full-band frequency model on 30 s of the grid k dt, first n samples."""
    t = np.arange(max(n, int(30.0 / dt))) * dt
    return valve_head(t, rig, mat)[:n]


def test_reference_rig_now_says_quadratic():
    r = load_rig("perugia")
    assert r.friction == "quadratic" and r.friction_unsteady == "none"


@pytest.mark.parametrize("adjust", ["dt", "wave_speed"])
@pytest.mark.parametrize("dt", [1e-3, 2.5e-3, 7e-4])
def test_grid_is_characteristic(rig, adjust, dt):
    a = 353.73
    n, dt2, a2 = grid(rig, a, dt, adjust)
    assert n * a2 * dt2 == pytest.approx(rig.pipe.length_m, rel=1e-13)
    assert n == round(rig.pipe.length_m / (a * dt))
    if adjust == "dt":
        assert a2 == a and dt2 == pytest.approx(dt, rel=0.5 / n)
    else:
        assert dt2 == dt and a2 == pytest.approx(a, rel=0.5 / n)


# --------------------------------------------------------------------------- agreement with the frequency model


@pytest.mark.parametrize("name, measured", [("elastic", 7.3e-5), ("A", 3e-6), ("B", 2.3e-5), ("hdpe_s1", 1e-6)])
def test_moc_solve_agrees_with_frequency_model(rig, name, measured):
    """Linear friction, on the MOC's own grid (every front on a grid point), 20 s at 1 ms.

    Measured max differences relative to hJ in the parametrisation; the elastic pipe's is
    the frequency model's own wrap-around (its oscillation is damped by friction only).
    """
    mat = load_material(name)
    r = moc_solve(rig, mat, 20.0, 1e-3, friction="linear")
    assert r.t_s[-1] == pytest.approx(20.0, abs=r.dt_s)
    hj = _joukowsky(rig, mat.wave_speed_m_s)
    diff = r.head_m - _long_reference(rig, mat, r.dt_s, r.t_s.size)
    assert np.abs(diff).max() < max(3 * measured, 2e-5) * hj
    assert np.abs(diff).max() < 1e-3 * hj


@pytest.mark.parametrize("name", ["elastic", "A", "B", "hdpe_s1"])
@pytest.mark.parametrize("offset", [0.0, 0.37e-3, 0.5e-3])
def test_moc_head_agrees_on_any_sample_grid(rig, name, offset):
    """moc_head on a 1 kHz record with 1 s before the trigger, the trigger between two samples.

    Measured at the default 2 ms MOC step: max 1.4 mm (B; 8e-5 hJ), RMS <= 0.7 mm (the
    elastic pipe's: the frequency model's wrap-around), whatever the offset.
    """
    mat = load_material(name)
    a, J, tau = _params(rig, mat)
    t = np.arange(-1000, 20000) * 1e-3 - offset
    h = moc_head(rig, a, J, tau, t)
    assert np.all(h[t < 0] == 0.0)
    after = t >= 0
    diff = (h - valve_head(t, rig, mat))[after]
    hj = _joukowsky(rig, a)
    assert np.abs(diff).max() < 2e-4 * hj
    assert np.sqrt(np.mean(diff**2)) < 1e-4 * hj


def test_moc_wrapper_on_its_grid(rig):
    mat = load_material("A")
    t, h = moc_valve_head(rig, mat, 5.0, 1e-3)
    r = moc_solve(rig, mat, 5.0, 1e-3)
    np.testing.assert_array_equal(h, r.head_m)
    np.testing.assert_array_equal(t, r.t_s)


def test_second_order_in_dt(rig):
    """Trapezoidal creep along the characteristics + semi-implicit friction: second order.

    A strong, fast element (J' = 0.5, tau = 10 ms) makes the error visible: halving dt
    quarters it (measured 8.6, 2.2, 0.58 mm at 2, 1, 0.5 ms; Covas's scheme, which takes
    the creep rate at the new node, gave 134, 66, 33 mm).
    """
    a = 353.73
    mat = Material(a, (KelvinVoigt.from_creep(0.5 / creep_scale(rig, a), 1e-2),))
    errs = []
    for dt in (2e-3, 1e-3):
        r = moc_solve(rig, mat, 5.0, dt)
        errs.append(np.abs(r.head_m - _long_reference(rig, mat, r.dt_s, r.t_s.size)).max())
    assert 0.15 < errs[1] / errs[0] < 0.35
    assert errs[1] < 5e-3


@pytest.mark.parametrize("rig_name", ["perugia", "imperial"])
@pytest.mark.parametrize("unsteady", ["none", "brunone"])
def test_moc_head_on_the_moc_grid_is_the_moc_with_the_step_inside(rig_name, unsteady):
    """Nonlinear laws: moc_head takes the trigger step through the MOC (full flow minus the linear
    step alone, plus the frequency model's step). On the MOC's own grid, where the step and every
    front fall on grid points, that is exactly the MOC of the full flow (moc_solve), step and all:
    the step meets the nonlinear friction as in the pipe."""
    r = with_valve_law(load_rig(rig_name), "imposed")
    mat = Material(r.nominal_wave_speed_m_s, load_material("A").elements)
    a, J, tau = _params(r, mat)
    sol = moc_solve(r, mat, 20.0, 1e-3, unsteady=unsteady)
    h = moc_head(r, a, J, tau, sol.t_s, dt_s=1e-3, unsteady=unsteady)
    assert sol.friction == "quadratic"
    assert np.abs(h - sol.head_m).max() < 5e-4


def test_moc_head_is_smooth_in_the_wave_speed(rig):
    """N is fixed by the nominal wave speed, so h(a) has no jumps: finite differences converge."""
    mat = load_material("A")
    a, J, tau = _params(rig, mat)
    t = np.arange(5000) * 1e-3
    h0 = moc_head(rig, a, J, tau, t)
    d1 = (moc_head(rig, a + 1e-2, J, tau, t) - h0) / 1e-2
    d2 = (moc_head(rig, a + 1e-3, J, tau, t) - h0) / 1e-3
    assert np.abs(d1 - d2).max() < 0.05 * np.abs(d1).max()
    assert np.abs(d1).max() > 0.01  # the head does depend on a


# --------------------------------------------------------------------------- analytic checks


def test_moc_first_plateau_frictionless_elastic(rig):
    """No friction, elastic: h = -B q(t) exactly until the reflection returns at 2L/a,
    and the reservoir does not see anything before L/a (causality on the grid)."""
    r0 = rig.with_changes(friction="none")
    el = load_material("elastic")
    res = moc_solve(r0, el, 2.0, 1e-3)
    L, a = r0.pipe.length_m, el.wave_speed_m_s
    B = a / (GRAVITY_M_S2 * r0.pipe.area_m2)
    before = res.t_s < 2 * L / a - res.dt_s / 2
    np.testing.assert_allclose(res.head_m[before], -B * flow_perturbation(res.t_s[before], r0), atol=1e-12)
    assert np.all(res.flow_reservoir_m3_s[res.t_s < L / a - res.dt_s / 2] == 0.0)
    assert np.abs(res.flow_reservoir_m3_s[res.t_s > L / a + 0.3]).max() > 0.5 * r0.steady_flow_m3_s
    assert res.head_m[before].max() == pytest.approx(_joukowsky(r0, a), rel=1e-5)


def test_quadratic_vs_linear_friction_first_wave(rig):
    """Linearisation error during the first 2L/a: small and bounded by line packing.

    After a full closure the tangent friction R q changes the friction slope by
    R Q0 = 2 J0, the quadratic law by J0; the difference of the line packing is at
    most J0 L = steady head loss (0.28 m). Measured: 0.19 m (1 % of hJ).
    """
    mat = load_material("A")
    lin = moc_solve(rig, mat, 0.6, 1e-3, friction="linear")
    quad = moc_solve(rig, mat, 0.6, 1e-3, friction="quadratic")
    first = lin.t_s < 2 * rig.pipe.length_m / mat.wave_speed_m_s
    d = np.abs(quad.head_m - lin.head_m)[first]
    assert 0.01 * rig.steady_head_loss_m < d.max() <= rig.steady_head_loss_m
    assert d.max() < 0.02 * _joukowsky(rig, mat.wave_speed_m_s)


@pytest.mark.parametrize("rig_name", ["perugia", "imperial"])
def test_final_levels_of_a_full_closure(rig_name):
    """Long after a full closure: quadratic -> the steady head loss h_f (the flow stopped,
    the friction drop vanished); the tangent R -> R L Q0 = 2 h_f; no friction -> 0."""
    r = load_rig(rig_name)
    mat = Material(r.nominal_wave_speed_m_s, load_material("A").elements)
    a, J, tau = _params(r, mat)
    t = np.arange(0, 90.0, 5e-3)
    tail = t > 85.0
    hf = r.steady_head_loss_m
    for law, level, tol in (("quadratic", hf, 0.02 * hf), ("linear", 2 * hf, 2e-3), ("none", 0.0, 2e-3)):
        h = moc_head(r, a, J, tau, t, friction=law, dt_s=4e-3)
        assert h[tail].mean() == pytest.approx(level, abs=tol), law
    assert r.linear_resistance * r.pipe.length_m * r.steady_flow_m3_s == pytest.approx(2 * hf)


def test_quadratic_vs_linear_on_the_reference_rig():
    """What the linearisation costs on material A over 20 s (issue 10): about 0.9 m RMS,
    1.9 m at most, 0.09 m RMS in the first 0.6 s, 1.2 m RMS at 5-10 s; the tangent R damps
    the oscillation about twice as fast (peak-to-peak at 15-20 s: 4.0 m vs 2.0 m)."""
    r = load_rig("perugia")
    a, J, tau = _params(r, load_material("A"))
    t = np.arange(20000) * 1e-3
    lin = moc_head(r, a, J, tau, t, friction="linear")
    quad = moc_head(r, a, J, tau, t, friction="quadratic")
    d = quad - lin
    assert 0.85 < np.sqrt(np.mean(d**2)) < 1.0
    assert 1.8 < np.abs(d).max() < 2.0
    assert np.sqrt(np.mean(d[t < 0.6] ** 2)) < 0.12
    late = t > 15.0
    assert np.ptp(quad[late]) > 1.7 * np.ptp(lin[late])


# --------------------------------------------------------------------------- unsteady friction


@pytest.mark.parametrize("rig_name, name", [("perugia", "A"), ("perugia", "elastic"), ("imperial", "B")])
def test_vardy_brown_moc_agrees_with_frequency_model(rig_name, name):
    """Linear steady + Vardy-Brown: the MOC's sum of exponentials vs the exact frequency-domain
    resistance R_u(s), to 1e-3 hJ (measured: 1.7 mm on perugia, 3.7 mm on imperial; the
    unsteady friction itself changes the head by 2-5 m)."""
    r = load_rig(rig_name).with_changes(friction="linear", friction_unsteady="vardy-brown")
    mat = Material(r.nominal_wave_speed_m_s, load_material(name).elements)
    a, J, tau = _params(r, mat)
    t = np.arange(-500, 20000) * 1e-3 - 0.3e-3
    after = t >= 0
    h = moc_head(r, a, J, tau, t)[after]
    ref = valve_head(t, r, mat)[after]
    hj = _joukowsky(r, a)
    assert np.abs(h - ref).max() < 1e-3 * hj
    steady_only = valve_head(t, r.with_changes(friction_unsteady="none"), mat)[after]
    assert np.abs(ref - steady_only).max() > 1.0  # the comparison is not trivial


def test_zielke_laminar_moc_agrees_with_frequency_model():
    """A laminar rig (Re 1500): Zielke's weighting function, exact in the frequency model
    (Bessel functions), 24 exponentials + quadrature tail in the MOC."""
    r0 = load_rig("perugia")
    r = r0.with_changes(steady_flow_m3_s=1500 * r0.fluid.kinematic_viscosity_m2_s * r0.pipe.area_m2
                        / r0.pipe.inner_diameter_m, friction="quadratic", friction_unsteady="vardy-brown")
    assert r.laminar and r.reynolds == pytest.approx(1500)
    mat = load_material("elastic")
    a, J, tau = _params(r, mat)
    t = np.arange(20000) * 1e-3
    h = moc_head(r, a, J, tau, t)  # laminar "quadratic" is Poiseuille, linear: the FD is exact
    np.testing.assert_array_equal(h, moc_head(r, a, J, tau, t, friction="linear"))
    ref = valve_head(t, r, mat)
    assert np.abs(h - ref).max() < 1e-3 * _joukowsky(r, a)
    assert np.abs(ref - valve_head(t, r.with_changes(friction_unsteady="none"), mat)).max() > 0.1 * _joukowsky(r, a)


def test_brunone_damps_and_vanishes_with_k3():
    r = load_rig("perugia")
    a, J, tau = _params(r, load_material("A"))
    t = np.arange(20000) * 1e-3
    quad = moc_head(r, a, J, tau, t, unsteady="none")
    bru = moc_head(r, a, J, tau, t, unsteady="brunone")
    late = t > 10.0
    assert np.ptp(bru[late]) < 0.85 * np.ptp(quad[late])  # extra damping (measured 6.2 m vs 8.2 m)
    assert np.sqrt(np.mean((bru - quad) ** 2)) > 0.5  # measured 1.4 m RMS
    tiny = moc_head(r.with_changes(brunone_k3=1e-9), a, J, tau, t, unsteady="brunone")
    assert np.abs(tiny - quad).max() < 1e-6


@pytest.mark.parametrize("friction", ["none", "linear", "quadratic"])
@pytest.mark.parametrize("unsteady", ["none", "vardy-brown", "brunone"])
def test_compiled_kernel_matches_numpy_reference(friction, unsteady):
    """The numba kernel against a straightforward numpy implementation (tests/moc_reference.py)
    on a tiny grid (6 reaches, 3 s): the same numbers to rounding."""
    r = load_rig("perugia")
    a, J, tau = _params(r, load_material("A"))
    n = 6
    dt = r.pipe.length_m / (n * a)
    q = flow_perturbation(np.arange(int(3.0 / dt)) * dt, r)
    h, q_res, q_val = run(r, J, tau, q, n, dt, a, friction, unsteady)
    h_ref, q_res_ref, _ = march_reference(r, J, tau, q, n, dt, a, friction, unsteady)
    np.testing.assert_allclose(h, h_ref, rtol=0, atol=1e-11)
    np.testing.assert_allclose(q_res, q_res_ref, rtol=0, atol=1e-14)
    np.testing.assert_array_equal(q_val, q)  # the imposed flow, as given
    assert np.abs(h).max() > 15.0


def test_custom_flow_partial_closure():
    """flow=: a half closure; with linear friction the frequency model with the same flow agrees."""
    r = load_rig("perugia").with_changes(friction="linear")
    mat = load_material("A")
    a, J, tau = _params(r, mat)
    t = np.arange(20000) * 1e-3
    half = lambda x: 0.5 * flow_perturbation(x, r)  # noqa: E731
    h = moc_head(r, a, J, tau, t, flow=half)
    ref = ValveHeadModel(r, t, band_hz=None, flow=half(t)).head(mat)
    assert np.abs(h - ref).max() < 2e-4 * _joukowsky(r, a)
    assert h.max() == pytest.approx(0.5 * moc_head(r, a, J, tau, t).max(), rel=1e-3)


def test_moc_rejects_bad_arguments(rig):
    mat = load_material("A")
    a, J, tau = _params(rig, mat)
    t = np.arange(100) * 1e-3
    with pytest.raises(ValueError, match="friction"):
        moc_solve(rig, mat, 1.0, 1e-3, friction="darcy")
    with pytest.raises(ValueError, match="unsteady"):
        moc_head(rig, a, J, tau, t, unsteady="zielke")
    with pytest.raises(ValueError):
        moc_solve(rig, mat, 1.0, -1e-3)
    with pytest.raises(ValueError):
        moc_solve(rig, mat, 1.0, 1e-3, adjust="length")
    with pytest.raises(ValueError, match="same length"):
        moc_head(rig, a, J, tau[:2], t)
    with pytest.raises(ValueError, match="retardation"):
        moc_head(rig, a, J, -tau, t)
    with pytest.raises(ValueError, match="wave speed"):
        moc_head(rig, -a, J, tau, t)
    assert np.all(moc_head(rig, a, J, tau, t - 1.0) == 0.0)  # a record that ends before the trigger


# --------------------------------------------------------------------------- the valve's orifice law


@pytest.mark.parametrize("friction", ["none", "linear", "quadratic"])
@pytest.mark.parametrize("unsteady", ["none", "brunone"])
def test_compiled_orifice_boundary_matches_numpy_reference(friction, unsteady):
    """The kernel's closed-form root of the valve's quadratic against numpy's polynomial roots
    (tests/moc_reference.py), on a tiny grid through the commanded closure."""
    r = load_rig("perugia")
    a, J, tau = _params(r, load_material("A"))
    n = 6
    dt = r.pipe.length_m / (n * a)
    opening = commanded_opening(r)(np.arange(int(3.0 / dt)) * dt)
    h, q_res, q_val = run(r, J, tau, None, n, dt, a, friction, unsteady, opening=opening)
    h_ref, q_res_ref, q_val_ref = march_reference(r, J, tau, None, n, dt, a, friction, unsteady, opening=opening)
    np.testing.assert_allclose(h, h_ref, rtol=0, atol=1e-10)
    np.testing.assert_allclose(q_val, q_val_ref, rtol=0, atol=1e-14)
    np.testing.assert_allclose(q_res, q_res_ref, rtol=0, atol=1e-13)
    assert np.abs(h).max() > 15.0


@pytest.mark.parametrize("friction", ["none", "linear", "quadratic"])
def test_valve_node_obeys_the_orifice_law_at_every_step(friction):
    """moc_solve follows the rig's valve law: with "orifice" the flow through the valve and the head
    upstream of it satisfy Q = Q0 tau(p) sqrt((Hv0 + h)/Hv0) at every step, p the commanded sigmoid
    in position; the flow is the imposed sigmoid's only with the law "imposed"."""
    r = load_rig("perugia").with_changes(friction=friction)
    assert r.valve.law == "orifice"
    sol = moc_solve(r, load_material("A"), 5.0, 1e-3)
    m = r.manoeuvre
    assert sol.valve_law == "orifice"
    np.testing.assert_array_equal(sol.position_pct, commanded_position_pct(sol.t_s, m.beta_per_s, m.gamma))
    Q = r.steady_flow_m3_s + sol.flow_valve_m3_s
    law = orifice_flow(r.valve.opening(sol.position_pct), sol.head_m, r.steady_flow_m3_s, r.valve_head_m)
    np.testing.assert_allclose(Q, law, rtol=0, atol=1e-12 * r.steady_flow_m3_s)
    assert np.all(Q >= 0) and Q[sol.t_s > 1.0].max() < 1e-3 * r.steady_flow_m3_s  # shut
    imposed = moc_solve(with_valve_law(r, "imposed"), load_material("A"), 5.0, 1e-3)
    assert imposed.valve_law == "imposed" and imposed.position_pct is None
    np.testing.assert_array_equal(imposed.flow_valve_m3_s, flow_perturbation(imposed.t_s, r))
    assert np.sqrt(np.mean((imposed.head_m - sol.head_m) ** 2)) > 0.5


def test_orifice_first_wave_frictionless_elastic():
    """No friction, elastic wall, until the reflection returns at 2L/a: the valve sees no pipe but
    its own wave, h = -B q, so the flow solves (Q0 + q)^2 = (Q0 tau)^2 (1 - B q / Hv0) in closed form."""
    r = load_rig("perugia").with_changes(friction="none")
    el = load_material("elastic")
    sol = moc_solve(r, el, 0.6, 1e-3)
    a, L, q0, hv0 = el.wave_speed_m_s, r.pipe.length_m, r.steady_flow_m3_s, r.valve_head_m
    B = a / (GRAVITY_M_S2 * r.pipe.area_m2)
    first = sol.t_s < 2 * L / a - sol.dt_s / 2
    K2 = (q0 * r.valve.opening(sol.position_pct[first])) ** 2 / hv0
    X = (-K2 * B + np.sqrt((K2 * B) ** 2 + 4 * K2 * (hv0 + B * q0))) / 2
    np.testing.assert_allclose(sol.flow_valve_m3_s[first], X - q0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(sol.head_m[first], -B * (X - q0), rtol=0, atol=1e-9)
    # the trigger's step: the commanded position starts 0.41 % closed, a butterfly passes 0.04 % less
    assert sol.flow_valve_m3_s[0] / q0 == pytest.approx(-3.3e-4, rel=0.05)


def test_no_flow_runs_back_in_through_the_valve():
    """A valve stopped at 10 % open on a low-head rig: the downsurge takes the head below the free
    discharge, where the orifice law passes no flow (not a negative one), and the flow resumes."""
    r = load_rig("perugia").with_changes(reservoir_head_m=5.0, friction="none")
    el = load_material("elastic")
    a, J, tau = _params(r, el)
    n = 50
    dt = r.pipe.length_m / (n * a)
    t = np.arange(int(4.0 / dt)) * dt
    opening = r.valve.opening(np.where(t < 0.1, 100.0 - 900.0 * t, 10.0))
    h, _, q = run(r, J, tau, None, n, dt, a, "none", "none", opening=opening)
    Q = r.steady_flow_m3_s + q
    below = r.valve_head_m + h < 0
    assert below.sum() > 100 and np.all(Q[below] == 0.0)
    assert np.all(Q >= 0.0) and Q[t > 3.0].max() > 0.05 * r.steady_flow_m3_s
    # on a sample grid too: the resampled flow never runs back in
    ts = np.arange(4000) * 1e-3
    tr = moc_transient(r, a, J, tau, ts, opening=lambda x: r.valve.opening(np.where(x < 0.1, 100.0 - 900.0 * x, 10.0)))
    assert np.all(r.steady_flow_m3_s + tr.flow_m3_s >= 0.0) and tr.head_m.min() < -r.valve_head_m - 5.0


def test_orifice_head_converges_in_dt():
    """The orifice law at the valve keeps the scheme second order: against a 0.25 ms solution,
    max errors measured 2.3, 0.53, 0.13 mm at 4, 2, 1 ms on material A (quadratic friction), the
    flow's 1.7e-5, 1.3e-6, 9e-8 of Q0. The default step (2 ms) is within 3e-5 of the Joukowsky head."""
    r = load_rig("perugia")
    a, J, tau = _params(r, load_material("A"))
    t = np.arange(-200, 8000) * 1e-3 - 0.37e-3
    ref = moc_transient(r, a, J, tau, t, opening=commanded_opening(r), dt_s=2.5e-4)
    errs, qerrs = [], []
    for dt in (4e-3, 2e-3, 1e-3):
        tr = moc_transient(r, a, J, tau, t, opening=commanded_opening(r), dt_s=dt)
        errs.append(np.abs(tr.head_m - ref.head_m).max())
        qerrs.append(np.abs(tr.flow_m3_s - ref.flow_m3_s).max() / r.steady_flow_m3_s)
    assert 0.15 < errs[1] / errs[0] < 0.35 and 0.15 < errs[2] / errs[1] < 0.35
    assert errs[1] < 3e-5 * _joukowsky(r, a) and qerrs[1] < 5e-6
    assert qerrs[2] < qerrs[1] < qerrs[0]
    default = moc_transient(r, a, J, tau, t, opening=commanded_opening(r))
    np.testing.assert_array_equal(default.head_m, moc_transient(r, a, J, tau, t, opening=commanded_opening(r),
                                                                dt_s=2e-3).head_m)
    assert np.all(ref.head_m[t < 0] == 0.0) and np.all(ref.flow_m3_s[t < 0] == 0.0)


def test_moc_transient_on_the_solver_grid_is_moc_solve():
    """On the solver's own grid the sample-grid transient (the trigger's flow step taken apart and
    put back at its exact instant) is the orifice-law MOC with the step inside."""
    r = load_rig("perugia")
    mat = Material(r.nominal_wave_speed_m_s, load_material("A").elements)
    a, J, tau = _params(r, mat)
    sol = moc_solve(r, mat, 20.0, 1e-3)
    tr = moc_transient(r, a, J, tau, sol.t_s, dt_s=1e-3, position=lambda x: commanded_position_pct(
        x, r.manoeuvre.beta_per_s, r.manoeuvre.gamma))
    assert np.abs(tr.head_m - sol.head_m).max() < 5e-4
    assert np.abs(tr.flow_m3_s - sol.flow_valve_m3_s).max() < 1e-6 * r.steady_flow_m3_s


def test_imposed_flow_paths_are_unchanged():
    """moc_head without a valve argument imposes the rig's sigmoid as the flow whatever rig.valve says
    (the fit's friction correction relies on it); position= with the law "imposed" imposes Q0 p/100;
    moc_transient returns the head moc_head does and the imposed flow."""
    r = load_rig("perugia")
    imposed = with_valve_law(r, "imposed")
    a, J, tau = _params(r, load_material("A"))
    t = np.arange(-300, 6000) * 1e-3 - 0.2e-3
    h = moc_head(r, a, J, tau, t)
    np.testing.assert_array_equal(h, moc_head(imposed, a, J, tau, t))
    tr = moc_transient(r, a, J, tau, t)
    np.testing.assert_array_equal(tr.head_m, h)
    np.testing.assert_array_equal(tr.flow_m3_s, flow_perturbation(t, r))
    m = r.manoeuvre
    by_position = moc_transient(imposed, a, J, tau, t, position=lambda x: commanded_position_pct(
        x, m.beta_per_s, m.gamma, 40.0))
    half = moc_transient(r, a, J, tau, t, flow=lambda x: 0.6 * flow_perturbation(x, r))
    np.testing.assert_allclose(by_position.head_m, half.head_m, rtol=0, atol=1e-9)
    np.testing.assert_allclose(by_position.flow_m3_s, half.flow_m3_s, rtol=0, atol=1e-15)


def test_valve_arguments_are_checked():
    r = load_rig("perugia")
    mat = load_material("A")
    a, J, tau = _params(r, mat)
    t = np.arange(100) * 1e-3
    with pytest.raises(ValueError, match="not several"):
        moc_head(r, a, J, tau, t, flow=lambda x: 0 * x, opening=commanded_opening(r))
    with pytest.raises(ValueError, match="opening must be finite and non-negative"):
        moc_head(r, a, J, tau, t, opening=lambda x: -1.0 + 0 * x)
    with pytest.raises(ValueError, match="valve must be one of orifice, imposed"):
        moc_solve(r, mat, 1.0, 1e-3, valve="butterfly")
    with pytest.raises(ValueError, match="positive steady head"):
        moc_head(r.with_changes(reservoir_head_m=0.1), a, J, tau, t, opening=commanded_opening(r))
