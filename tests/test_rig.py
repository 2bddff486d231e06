"""The one physical model of the simulated rig."""

import threading

import numpy as np
import pytest

from velab.config import load_material, load_rig
from velab.rig import Manoeuvre
from velab.synth import transient
from velab.valvelaw import commanded_position_pct
from velab.simulators.clock import ManualClock, RealTimeClock
from velab.simulators.rig import CommandRefused, SimulatedRig, ValveState


@pytest.fixture
def rig():
    return SimulatedRig(load_rig("perugia"), load_material("A"), ManualClock(), seed=1)


def test_steady_state_analog_inputs(rig):
    t = np.linspace(0, 1, 1000)
    ai = rig.analog_inputs(t)
    r = rig.rig
    assert ai.shape == (1000, 4)
    p = (ai[:, 0] - 4) / 16 * r.transducer.full_scale_pa
    assert p.mean() == pytest.approx(r.steady_head_m * r.fluid.density_kg_m3 * 9.81, rel=1e-3)
    assert p.std() == pytest.approx(2e-4 * 6e5, rel=0.15)
    assert ai[:, 1].mean() == pytest.approx(20.0, abs=0.01)
    assert np.all(ai[:, 2:] == 4.0)
    assert rig.flow_m3_s(t) == pytest.approx(r.steady_flow_m3_s)


def test_noise_is_a_function_of_time_not_of_call_order(rig):
    t = np.array([0.1, 0.2, 0.3])
    a = rig.analog_inputs(t)
    rig.analog_inputs(np.linspace(0, 5, 777))
    assert np.array_equal(rig.analog_inputs(t[::-1])[::-1], a)
    other = SimulatedRig(rig.rig, rig.material, ManualClock(), seed=2)
    assert not np.array_equal(other.analog_inputs(t)[:, 0], a[:, 0])


def test_transient_is_velab_model_for_commanded_manoeuvre(rig):
    rig.set_manoeuvre(40.0, -6.0)
    rig.arm()
    rig.clock.advance(2.0)
    t0 = rig.trigger()
    assert rig.trigger_time == t0 == 2.0 and rig.state() is ValveState.RUNNING
    tau = np.arange(0, 3, 1e-3)
    # the rig's own valve law (orifice, on the commanded sigmoid in position) and friction law
    # (quadratic): the time-domain model
    grid = np.arange(0, 20 + 1e-4, 2e-4)
    ref, q_ref = transient(grid, rig.rig.with_changes(manoeuvre=Manoeuvre(40.0, -6.0)), rig.material)
    ref_i = np.interp(tau, grid, ref)
    assert rig.head_m(t0 + tau) - rig.rig.steady_head_m == pytest.approx(ref_i, abs=0.02)
    assert rig.head_m(np.array([t0 - 0.1]))[0] == rig.rig.steady_head_m
    assert rig.valve_position(t0 + tau) == pytest.approx(commanded_position_pct(tau, 40.0, -6.0), abs=1e-9)
    q = rig.flow_m3_s(t0 + tau)
    q0 = rig.rig.steady_flow_m3_s
    assert q == pytest.approx(q0 + np.interp(tau, grid, q_ref), rel=1e-6, abs=1e-9)
    assert np.abs(q - q0 / (1 + np.exp(40.0 * tau - 6.0))).max() > 0.2 * q0  # the sigmoid is not the flow
    rig.clock.advance(1.0)
    assert rig.state() is ValveState.DONE


def test_the_valve_is_done_when_the_commanded_stroke_has_0_1_percent_left(rig):
    m = Manoeuvre(40.0, -6.0)
    assert commanded_position_pct(m.closed_s, 40.0, -6.0) == pytest.approx(0.1)
    rig.set_manoeuvre(40.0, -6.0)
    rig.arm()
    t0 = rig.trigger()
    rig.clock.advance(m.closed_s - 1e-3)
    assert rig.state() is ValveState.RUNNING
    rig.clock.advance(2e-3)
    assert rig.state() is ValveState.DONE
    assert Manoeuvre(1.0, 8.0).closed_s == 0.0  # a sigmoid that starts below 0.1 % is closed at the trigger


def test_hold_freezes_valve_and_flow(rig):
    rig.arm()
    rig.trigger()
    rig.clock.advance(0.17)
    rig.hold()
    t = rig.clock.now() + np.array([0.0, 1.0, 5.0])
    pos = rig.valve_position(t)
    assert pos == pytest.approx([pos[0]] * 3) and 30 < pos[0] < 70
    assert rig.state() is ValveState.HOLDING
    # the surge is smaller than for a full closure
    full = SimulatedRig(rig.rig, rig.material, ManualClock(), seed=1)
    full.arm()
    full.trigger()
    tt = np.linspace(0, 3, 3000)
    assert rig.head_m(tt).max() < full.head_m(tt).max()


def test_commands_refused_in_wrong_state(rig):
    with pytest.raises(CommandRefused):
        rig.trigger()
    rig.arm()
    with pytest.raises(CommandRefused) as ei:
        rig.set_manoeuvre(10.0, -3.0)
    assert ei.value.code == 6
    rig.abort()
    assert rig.state() is ValveState.ABORTED
    rig.reset()
    assert rig.state() is ValveState.IDLE and rig.trigger_time is None


def test_flowmeter_refresh_noise_and_totaliser(rig):
    rig.clock.advance(10.0)
    assert rig.flowmeter_value(10.1) == rig.flowmeter_value(10.4)
    assert rig.flowmeter_value(10.1) != rig.flowmeter_value(10.6)
    assert rig.totalizer_m3(10.0) == pytest.approx(10.0 * rig.rig.steady_flow_m3_s)
    rig.arm()
    rig.trigger()
    v_end = rig.totalizer_m3(10.0 + 5.0)
    assert 10.0 * rig.rig.steady_flow_m3_s < v_end < 10.2 * rig.rig.steady_flow_m3_s + 0.2 * rig.rig.steady_flow_m3_s


def test_clocks():
    c = ManualClock()
    c.sleep(0.5)
    assert c.now() == 0.5
    with pytest.raises(ValueError):
        c.advance(-1)
    r = RealTimeClock()
    a = r.now()
    r.sleep(0.01)
    assert r.now() - a >= 0.009


def _arming_finished():
    """Join the actuator's arming computation (arm(background=True)): its end is a state of the rig's."""
    for th in threading.enumerate():
        if th.name == "sim-valve-arming":
            th.join(60)


def test_arming_in_the_background_reports_idle_until_armed(rig):
    rig.set_manoeuvre(30.0, -5.5)
    rig.arm(background=True)  # as the Modbus actuator does on ARM: the reply first
    assert rig.state() is ValveState.IDLE  # the transient is being computed
    with pytest.raises(CommandRefused, match="arm first"):
        rig.trigger()
    _arming_finished()
    assert rig.state() is ValveState.ARMED
    rig.clock.advance(1.0)
    rig.trigger()
    rig.clock.advance(-(-5.5) / 30.0)  # half-way in position
    assert rig.valve_position(np.array([rig.clock.now()]))[0] == pytest.approx(50.0, abs=0.5)


def test_abort_while_arming_cancels_it(rig):
    rig.arm(background=True)
    rig.abort()
    assert rig.state() is ValveState.ABORTED
    _arming_finished()
    assert rig.state() is ValveState.ABORTED  # the computation's result was dropped
    with pytest.raises(CommandRefused):
        rig.trigger()
    rig.reset()
    assert rig.state() is ValveState.IDLE


def test_a_manoeuvre_changed_while_arming_is_the_one_armed(rig):
    rig.set_manoeuvre(30.0, -5.5)
    rig.arm(background=True)
    rig.set_manoeuvre(20.0, -5.0)  # still IDLE: allowed, the arming starts over with it
    _arming_finished()
    assert rig.state() is ValveState.ARMED
    rig.trigger()
    rig.clock.advance(0.25)  # -gamma / beta: half-way for 20 / -5, 83 % closed for 30 / -5.5
    assert rig.valve_position(np.array([rig.clock.now()]))[0] == pytest.approx(50.0, abs=0.5)
