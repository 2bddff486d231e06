"""The physics of the simulated rig: the actuator moves the valve along the commanded sigmoid in
position, the flow obeys the rig's valve law on that position (the orifice law of the rig files,
physics.md section 10), the head is velab's model of that, and every device shows the same."""

from __future__ import annotations

import numpy as np
import pytest

from velab.config import load_material, load_rig
from velab.model import ValveHeadModel, flow_perturbation
from velab.simulators.clock import ManualClock
from velab.simulators.modbus_devices import SimValveActuator
from velab.simulators.rig import TRANSIENT_S, SimulatedRig
from velab.synth import transient, transient_head, with_valve_law
from velab.valvelaw import commanded_position_pct, orifice_flow

TAU = np.arange(0, 20 + 1e-4, 2e-4)


def _run(rig, *, end=0.0, seize_after=None, hold_at=None, **options):
    # the transient on TAU's span, as the references here (the MOC's last digits depend on the span);
    # the default span and what follows it: the tests at the end
    options.setdefault("transient_s", TAU[-1])
    sim = SimulatedRig(rig, load_material("A"), ManualClock(), seed=1, **options)
    m = rig.manoeuvre
    sim.set_manoeuvre(m.beta_per_s, m.gamma, end)
    sim.faults.valve_fault_after_s = seize_after
    sim.arm()
    t0 = sim.trigger()
    if hold_at is not None:
        sim.clock.advance(hold_at)
        sim.hold()
    return sim, t0


def _moved(rig, end, freeze):
    """Where the actuator moves the valve: the commanded sigmoid in position, stopped at freeze."""
    m = rig.manoeuvre

    def p(t):
        t = np.minimum(t, freeze) if freeze is not None else t
        return commanded_position_pct(t, m.beta_per_s, m.gamma, end)
    return p


def _check_orifice_law(sim, t0, tol=2e-3):
    """The flow the simulator shows is the orifice law's on the position it shows and the head it
    shows (up to the linear interpolation of its 0.2 ms grid: about 1e-3 of Q0 at the fastest closure)."""
    rig = sim.rig
    t = t0 + np.concatenate([np.linspace(0.0, 0.5, 1237), np.linspace(0.5, 20.0, 3001)])
    q = sim.flow_m3_s(t)
    law = orifice_flow(rig.valve.opening(sim.valve_position(t)), sim.head_m(t) - rig.steady_head_m,
                       rig.steady_flow_m3_s, rig.valve_head_m)
    assert np.abs(q - law).max() < tol * rig.steady_flow_m3_s


@pytest.mark.parametrize("rig_name", ["perugia", "imperial"])
def test_full_closure_is_the_orifice_law_with_the_rigs_friction(rig_name):
    rig = load_rig(rig_name)
    assert rig.valve.law == "orifice" and rig.friction == "quadratic"
    sim, t0 = _run(rig)
    h = sim.head_m(t0 + TAU) - rig.steady_head_m
    h_ref, q_ref = transient(TAU, rig, sim.material)
    np.testing.assert_allclose(h, h_ref, atol=1e-9)
    np.testing.assert_allclose(sim.flow_m3_s(t0 + TAU), rig.steady_flow_m3_s + q_ref, rtol=0, atol=1e-15)
    m = rig.manoeuvre
    np.testing.assert_allclose(sim.valve_position(t0 + TAU), commanded_position_pct(TAU, m.beta_per_s, m.gamma),
                               rtol=0, atol=1e-9)
    _check_orifice_law(sim, t0)
    # the flow falls later and faster than the sigmoid in position says: not the imposed flow, nor its head
    q = sim.flow_m3_s(t0 + TAU) / rig.steady_flow_m3_s
    sigmoid = 1 + flow_perturbation(TAU, rig) / rig.steady_flow_m3_s
    assert TAU[np.argmax(q < 0.9)] > TAU[np.argmax(sigmoid < 0.9)] + 0.03
    assert np.sqrt(np.mean((h - transient_head(TAU, rig, sim.material)) ** 2)) > 0.5


def test_partial_closure_passes_what_the_orifice_law_lets_through():
    """A closure to 50 % open: a butterfly at half stroke still passes 3/4 of the flow; the valve then
    stays there and the flow swings with the head about tau(50 %) Q0."""
    rig = load_rig("perugia")
    sim, t0 = _run(rig, end=50.0)
    h = sim.head_m(t0 + TAU) - rig.steady_head_m
    h_ref, q_ref = transient(TAU, rig, sim.material, position=_moved(rig, 50.0, None))
    np.testing.assert_allclose(h, h_ref, atol=1e-9)
    np.testing.assert_allclose(sim.flow_m3_s(t0 + TAU), rig.steady_flow_m3_s + q_ref, rtol=0, atol=1e-15)
    _check_orifice_law(sim, t0)
    assert sim.valve_position(t0 + np.array([10.0]))[0] == pytest.approx(50.0, abs=1e-6)
    tau50 = float(rig.valve.opening(50.0))
    assert tau50 == pytest.approx(1 / np.sqrt(0.95 + 0.05 * 16))
    late = TAU > 15.0
    assert np.mean(sim.flow_m3_s(t0 + TAU[late])) == pytest.approx(tau50 * rig.steady_flow_m3_s, rel=0.01)
    full = transient(TAU, rig, sim.material)[0]
    first = TAU < 0.5
    assert 0.2 * full[first].max() < h[first].max() < 0.5 * full[first].max()


@pytest.mark.parametrize("friction, valve", [("quadratic", "orifice"), ("linear", "orifice"), ("linear", "imposed")])
def test_seized_valve_stops_and_the_flow_follows_its_law(friction, valve):
    """The valve seizes 0.12 s after the trigger (mid-stroke): the position freezes there; with the
    orifice law the flow is what the frozen opening lets through at the head of the moment, with the
    imposed law (a stored rig's) the flow Q0 p/100 freezes and the frequency model is exact."""
    rig = with_valve_law(load_rig("perugia").with_changes(friction=friction), valve)
    sim, t0 = _run(rig, seize_after=0.12)
    pos = sim.valve_position(t0 + np.array([0.12, 1.0, 10.0]))
    assert pos == pytest.approx([pos[0]] * 3) and 50 < pos[0] < 90
    h = sim.head_m(t0 + TAU) - rig.steady_head_m
    h_ref, q_ref = transient(TAU, rig, sim.material, position=_moved(rig, 0.0, 0.12))
    np.testing.assert_allclose(h, h_ref, atol=1e-9)
    np.testing.assert_allclose(sim.flow_m3_s(t0 + TAU), rig.steady_flow_m3_s + q_ref, rtol=0, atol=1e-15)
    if valve == "orifice":
        _check_orifice_law(sim, t0)
    else:  # the frequency model with the same frozen flow
        q = lambda x: rig.steady_flow_m3_s * (_moved(rig, 0.0, 0.12)(x) / 100 - 1)  # noqa: E731
        ref = ValveHeadModel(rig, TAU, band_hz=None, flow=q(TAU)).head(sim.material)
        np.testing.assert_allclose(h, ref, atol=1e-9)
        np.testing.assert_allclose(sim.flow_m3_s(t0 + TAU), rig.steady_flow_m3_s + q(TAU), rtol=1e-12)
    # a frozen, partly open valve: the surge is far below a full closure's
    assert h.max() < 0.6 * transient(TAU, rig, sim.material)[0].max()


def test_hold_recomputes_with_the_frozen_position():
    rig = load_rig("perugia")
    sim, t0 = _run(rig, hold_at=0.17)
    h = sim.head_m(t0 + TAU) - rig.steady_head_m
    h_ref, _ = transient(TAU, rig, sim.material, position=_moved(rig, 0.0, 0.17))
    np.testing.assert_allclose(h, h_ref, atol=1e-9)
    _check_orifice_law(sim, t0)
    # the head up to the hold is the full closure's (the hold changes nothing before it)
    full = transient(TAU, rig, sim.material)[0]
    before = TAU < 0.165  # (the MOC's 2 ms grid and its cubic stencil reach a step past the hold)
    np.testing.assert_allclose(h[before], full[before], atol=2e-3)


def test_every_device_shows_the_same_valve():
    """The actuator's position register, the ADC's position channel and the flowmeter show the
    position the actuator moved the valve to and the flow the orifice law let through."""
    rig = load_rig("perugia")
    sim, t0 = _run(rig, end=20.0, position_noise_pct=0.0, flow_noise_rel=0.0, flow_update_s=0.25)
    actuator = SimValveActuator("valve", sim)
    for tau in (0.0, 0.15, 0.2, 0.25, 1.0, 5.0):
        t = t0 + tau
        sim.clock.advance(t - sim.clock.now())
        actuator.refresh(t)
        pos = float(sim.valve_position(np.array([t]))[0])
        assert actuator.get("position") == pytest.approx(pos, abs=1e-4)  # float32 register
        assert float(sim.clean_inputs(np.array([t]))[0, 1]) == pytest.approx(4.0 + 16.0 * pos / 100.0, abs=1e-12)
        tu = sim.flowmeter_update_time(t)
        assert sim.flowmeter_value(t) == pytest.approx(float(sim.flow_m3_s(np.array([tu]))[0]), rel=1e-12)
    # at 20 % open a butterfly (with its 5 % share of the loss) passes about a fifth of Q0
    assert sim.flowmeter_value(t0 + 5.0) == pytest.approx(float(rig.valve.opening(20.0)) * rig.steady_flow_m3_s,
                                                          rel=0.15)


def _flat_s(h: np.ndarray, dt: float) -> float:
    """The longest stretch (s) over which the noise-free head does not change at all."""
    moving = np.flatnonzero(np.abs(np.diff(h)) > 1e-12)
    edges = np.concatenate([[-1], moving, [h.size - 1]])
    return float(np.max(np.diff(edges)) * dt)


def test_a_default_30_s_run_has_no_flat_tail_and_settles_to_the_reservoirs_head():
    """Issue 50: the transient was computed for 20 s and held, so a 30 s run ended with 10 s of dead-flat head
    below the steady head; a closed valve's head tends to the reservoir's."""
    rig = load_rig("perugia")
    sim, t0 = _run(rig, transient_s=TRANSIENT_S)  # (the default)
    dt = 1e-3
    t = t0 + np.arange(0.0, 30.0, dt)
    h = sim.head_m(t)
    tail = h[t >= t0 + 20.0]
    assert _flat_s(tail, dt) < 0.05  # it still moves to the end of the record
    assert np.std(tail) > 0.01
    last = h[t >= t0 + 27.0]
    # its last seconds oscillate about the reservoir's head, above the steady head it started from
    assert abs(np.mean(last) - rig.reservoir_head_m) < 0.1 < rig.reservoir_head_m - rig.steady_head_m
    assert np.mean(last) > rig.steady_head_m + 0.2


@pytest.mark.parametrize("end", [0.0, 30.0])
def test_beyond_the_computed_transient_the_head_relaxes_to_the_rigs_end_state(end):
    """Past ``transient_s`` the head continues from the grid's last value (no step) towards where the rig
    settles: the reservoir's head for a closed valve, the last period's mean for one left partly open."""
    rig = load_rig("perugia")
    sim, t0 = _run(rig, end=end, transient_s=6.0)
    dt = 1e-3
    t = t0 + np.arange(0.0, 120.0, dt)
    h = sim.head_m(t)
    join = np.searchsorted(t, t0 + 6.0)
    slope = np.abs(np.diff(h[join - 6:join - 1])).max()  # (m per sample just before it)
    assert abs(h[join + 1] - h[join - 1]) <= 2 * slope + 1e-3  # continuous at the grid's end: no step
    assert _flat_s(h[(t > t0 + 6.0) & (t < t0 + 20.0)], dt) < 0.05  # still moving after it
    settled = h[-1000:]
    assert np.ptp(settled) < 1e-3  # settled
    if end == 0.0:
        assert settled.mean() == pytest.approx(rig.reservoir_head_m, abs=0.01)
    else:  # partly open: about the steady head the smaller flow leaves (the last period's mean)
        assert abs(settled.mean() - rig.steady_head_m) < 0.5
