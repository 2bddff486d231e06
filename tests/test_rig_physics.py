"""The physics of the simulated rig: heads from the rig's friction law, for the commanded manoeuvre."""

from __future__ import annotations

import numpy as np
import pytest

from velab.config import load_material, load_rig
from velab.model import ValveHeadModel, flow_perturbation
from velab.simulators.clock import ManualClock
from velab.simulators.rig import SimulatedRig
from velab.synth import transient_head

TAU = np.arange(0, 20 + 1e-4, 2e-4)


def _run(rig, *, end=0.0, seize_after=None, hold_at=None):
    sim = SimulatedRig(rig, load_material("A"), ManualClock(), seed=1)
    m = rig.manoeuvre
    sim.set_manoeuvre(m.beta_per_s, m.gamma, end)
    sim.faults.valve_fault_after_s = seize_after
    sim.arm()
    t0 = sim.trigger()
    if hold_at is not None:
        sim.clock.advance(hold_at)
        sim.hold()
    return sim, t0


def _opening_flow(rig, end, freeze):
    """The valve flow perturbation the simulated actuator imposes (linear valve characteristic)."""
    m, q0 = rig.manoeuvre, rig.steady_flow_m3_s

    def q(t):
        t = np.minimum(t, freeze) if freeze is not None else t
        return q0 * (end + (100 - end) / (1 + np.exp(m.beta_per_s * t + m.gamma))) / 100 - q0
    return q


@pytest.mark.parametrize("rig_name", ["perugia", "imperial"])
def test_full_closure_uses_the_rigs_quadratic_friction(rig_name):
    rig = load_rig(rig_name)
    sim, t0 = _run(rig)
    h = sim.head_m(t0 + TAU) - rig.steady_head_m
    np.testing.assert_allclose(h, transient_head(TAU, rig, sim.material), atol=1e-9)
    lin = transient_head(TAU, rig.with_changes(friction="linear"), sim.material)
    assert np.sqrt(np.mean((h - lin)[TAU > 5] ** 2)) > 0.3  # not the linearised model's head


def test_partial_closure_imposes_the_partial_flow():
    rig = load_rig("perugia")
    sim, t0 = _run(rig, end=50.0)
    h = sim.head_m(t0 + TAU) - rig.steady_head_m
    np.testing.assert_allclose(h, transient_head(TAU, rig, sim.material, flow=_opening_flow(rig, 50.0, None)),
                               atol=1e-9)
    full = transient_head(TAU, rig, sim.material)
    first = TAU < 0.5
    # half the flow change, about half the surge (friction makes it not exactly half)
    assert h[first].max() == pytest.approx(0.5 * full[first].max(), rel=0.02)
    assert sim.flow_m3_s(t0 + np.array([10.0]))[0] == pytest.approx(0.5 * rig.steady_flow_m3_s, rel=1e-6)


@pytest.mark.parametrize("friction", ["quadratic", "linear"])
def test_seized_valve_freezes_the_flow_and_the_head_follows(friction):
    """The valve seizes 0.12 s after the trigger (mid-stroke): the opening, hence the imposed flow,
    freezes there; the head is the model's response to that interrupted closure."""
    rig = load_rig("perugia").with_changes(friction=friction)
    sim, t0 = _run(rig, seize_after=0.12)
    pos = sim.valve_position(t0 + np.array([0.12, 1.0, 10.0]))
    assert pos == pytest.approx([pos[0]] * 3) and 50 < pos[0] < 90
    h = sim.head_m(t0 + TAU) - rig.steady_head_m
    q = _opening_flow(rig, 0.0, 0.12)
    np.testing.assert_allclose(h, transient_head(TAU, rig, sim.material, flow=q), atol=1e-9)
    if friction == "linear":  # the frequency model with the same frozen flow
        ref = ValveHeadModel(rig, TAU, band_hz=None, flow=q(TAU)).head(sim.material)
        np.testing.assert_allclose(h, ref, atol=1e-9)
    # a frozen, partly open valve: the surge is far below a full closure's
    assert h.max() < 0.6 * transient_head(TAU, rig, sim.material).max()


def test_hold_recomputes_with_the_frozen_opening():
    rig = load_rig("perugia")
    sim, t0 = _run(rig, hold_at=0.17)
    h = sim.head_m(t0 + TAU) - rig.steady_head_m
    np.testing.assert_allclose(h, transient_head(TAU, rig, sim.material, flow=_opening_flow(rig, 0.0, 0.17)),
                               atol=1e-9)
    assert flow_perturbation(np.array([0.17]), rig)[0] == pytest.approx(
        _opening_flow(rig, 0.0, 0.17)(np.array([5.0]))[0])
