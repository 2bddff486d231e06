"""The head along the pipe (physics.md section 12): the frequency model at a section x, its Jacobian, and
the time-domain model's sections against it."""

import numpy as np
import pytest

from velab.config import load_rig
from velab.fitting.engine import HeadEvaluator
from velab.model import ValveHeadModel
from velab.moc import moc_head, moc_transient
from velab.valvelaw import commanded_position_pct

A, J, TAU = 353.73, np.array([0.05, 0.02]), np.array([0.02, 0.5])


@pytest.fixture(scope="module")
def rig():
    return load_rig("perugia").with_changes(friction="linear")


def test_section_at_the_valve_is_the_valve_head_exactly(rig):
    t = np.arange(-0.2, 5, 1e-3)
    L = rig.pipe.length_m
    h = ValveHeadModel(rig, t).head_params(A, J, TAU)
    np.testing.assert_array_equal(ValveHeadModel(rig, t, position_m=L).head_params(A, J, TAU), h)
    np.testing.assert_array_equal(HeadEvaluator(rig, t, position_m=L).head(A, J, TAU), HeadEvaluator(rig, t).head(A, J, TAU))


def test_lossless_elastic_section_is_the_valve_head_delayed(rig):
    """No friction, no creep: before the first reflection reaches x, the head at x is the valve's delayed by
    (L - x)/a, and its plateau is Joukowsky's a Q0 / (g A)."""
    r = rig.with_changes(friction="none")
    L = r.pipe.length_m
    dt = 1e-4
    t = np.arange(0, 0.9, dt)
    x = 0.8 * L
    delay = (L - x) / A
    hv = ValveHeadModel(r, t, band_hz=None).head_params(A, [], [])
    hx = ValveHeadModel(r, t, band_hz=None, position_m=x).head_params(A, [], [])
    first_back = (L + x) / A  # the reflection from the reservoir comes back to x
    k = int(round(delay / dt))
    sel = (t >= delay) & (t < first_back - 0.01)
    np.testing.assert_allclose(hx[sel], hv[np.flatnonzero(sel) - k], atol=2e-3 * r.joukowsky_head_m(A))
    assert np.abs(hx[t < delay - 0.01]).max() < 1e-3 * r.joukowsky_head_m(A)
    plateau = hx[(t > delay + 0.35) & (t < first_back - 0.01)]  # the closure all but done (0.3 % of Q0 left)
    assert plateau.size > 50
    assert plateau.mean() == pytest.approx(r.joukowsky_head_m(A), rel=5e-3)


def test_section_near_the_reservoir_has_no_perturbation(rig):
    t = np.arange(0, 5, 1e-3)
    hj = rig.joukowsky_head_m(A)
    h = ValveHeadModel(rig, t, position_m=1e-6).head_params(A, J, TAU)
    assert np.abs(h).max() < 1e-6 * hj
    h1 = ValveHeadModel(rig, t, position_m=1.0).head_params(A, J, TAU)
    assert 0.01 * hj < np.abs(h1).max() < 0.05 * hj  # grows from 0 with x


@pytest.mark.parametrize("x", [0.0, -1.0, 200.0])
def test_section_outside_the_pipe_is_refused(rig, x):
    with pytest.raises(ValueError, match="section's position"):
        ValveHeadModel(rig, np.arange(0, 1, 1e-3), position_m=x)


def test_section_jacobian_is_the_finite_difference(rig):
    t = np.arange(-0.5, 10, 1e-3)
    ev = HeadEvaluator(rig, t, band_hz=None, position_m=41.0)
    h0, jac = ev.head_jac_x(A, J, TAU)
    np.testing.assert_allclose(h0, ValveHeadModel(rig, t, band_hz=None, position_m=41.0).head_params(A, J, TAU),
                               rtol=0, atol=1e-10)
    eps = 1e-6
    pairs = [(lambda e: (A * np.exp(e), J, TAU), 0), (lambda e: (A, J * np.exp([e, 0]), TAU), 1),
             (lambda e: (A, J, TAU * np.exp([0, e])), 4)]
    for f, row in pairs:
        fd = (ev.head(*f(eps)) - ev.head(*f(-eps))) / (2 * eps)
        assert np.abs(jac[row] - fd).max() < 1e-6 * np.abs(fd).max()


def test_moc_sections_agree_with_the_frequency_model(rig):
    """Linear friction, imposed flow, the trigger between samples: the MOC's sections within 2e-4 of the
    Joukowsky head of the frequency model's (the valve's agreement); a section at L is the valve's head."""
    t = np.arange(-0.5, 20, 1e-3) + 3e-4
    L = rig.pipe.length_m
    xs = (0.4 * L, 10.0, L)
    hm = moc_head(rig, A, J, TAU, t, sections_m=xs)
    hj = rig.joukowsky_head_m(A)
    for i, x in enumerate(xs):
        hf = ValveHeadModel(rig, t, band_hz=None, position_m=x).head_params(A, J, TAU)
        assert np.abs(hm[i] - hf).max() < 2e-4 * hj, x
    np.testing.assert_array_equal(hm[2], moc_head(rig, A, J, TAU, t))


def test_moc_sections_with_the_valve_law_and_quadratic_friction(rig):
    """Nonlinear: the valve's section is the valve's head; mid-pipe is smooth (no front straddled) and its
    surge lies between the reservoir's 0 and the valve's."""
    q = rig.with_changes(friction="quadratic")
    m = q.manoeuvre
    t = np.arange(-0.5, 10, 1e-3) + 3e-4
    L = q.pipe.length_m
    tr = moc_transient(q, A, J, TAU, t, position=lambda x: commanded_position_pct(x, m.beta_per_s, m.gamma),
                       sections_m=(0.4 * L, L))
    np.testing.assert_array_equal(tr.section_heads_m[1], tr.head_m)
    mid = tr.section_heads_m[0]
    assert 0.5 * tr.head_m.max() < mid.max() <= tr.head_m.max()
    assert np.abs(np.diff(mid)).max() < 0.35  # the steepest front of the closure, not a jump
