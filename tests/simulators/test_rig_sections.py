"""The simulated rig with several transducers: the head at every section of its rig from one run of the
rig's own model (the MOC with its friction and valve law: velab.synth.transient_at_sections), each on its
own steady head with its own noise, on its own ADC input (the valve's 0, the position 1, the others 2, 3);
the same at both simulated ADCs."""

from __future__ import annotations

import numpy as np
import pytest

from velab.config import load_material, load_rig
from velab.errors import ConfigError
from velab.rig import GRAVITY_M_S2, Section
from velab.simulators.clock import ManualClock
from velab.simulators.modbus_devices import SimModbusADC
from velab.simulators.rig import SimulatedRig
from velab.synth import transient, transient_at_sections

MID_X = 41.032


@pytest.fixture(scope="module")
def triggered():
    rig = load_rig("perugia_two_sections")
    sim = SimulatedRig(rig, load_material("A"), ManualClock(), seed=3)
    sim.arm()
    return sim, sim.trigger()


def _mA(head_m, rig):
    return 4.0 + 16.0 * head_m * rig.fluid.density_kg_m3 * GRAVITY_M_S2 / rig.transducer.full_scale_pa


def test_the_wiring_the_valves_transducer_on_input_0_the_others_from_input_2(triggered):
    sim, _ = triggered
    assert [sim.input_of(n) for n in ("valve", "mid")] == [0, 2]
    with pytest.raises(KeyError):
        sim.input_of("upstream")


def test_before_the_trigger_each_transducer_reads_its_own_steady_head_with_its_own_noise():
    rig = load_rig("perugia_two_sections")
    sim = SimulatedRig(rig, load_material("A"), ManualClock(), seed=3)
    t = np.arange(20000) / 10000.0
    mA = sim.analog_inputs(t)
    assert np.mean(mA[:, 0]) == pytest.approx(_mA(rig.steady_head_m, rig), abs=2e-3)
    assert np.mean(mA[:, 2]) == pytest.approx(_mA(rig.steady_head_at_m(MID_X), rig), abs=2e-3)
    assert np.mean(mA[:, 3]) == 4.0  # input 3: spare
    noise = mA - mA.mean(axis=0)
    assert np.std(noise[:, 2]) == pytest.approx(np.std(noise[:, 0]), rel=0.05)  # the same transducer model
    assert abs(np.corrcoef(noise[:, 0], noise[:, 2])[0, 1]) < 0.05  # ... and its own noise


def test_after_the_trigger_the_heads_are_one_run_of_the_rigs_model(triggered):
    sim, t0 = triggered
    rig = sim.rig
    tau = np.arange(0.0, 20.0 + 1e-4, sim.grid_dt_s)
    heads, q = transient_at_sections(tau, rig, sim.material)
    t = t0 + np.linspace(0.0, 19.0, 3001)
    grid = np.round((t - t0) / sim.grid_dt_s).astype(int)
    t = t0 + grid * sim.grid_dt_s  # on the grid: no interpolation
    np.testing.assert_allclose(sim.head_m(t, 1), rig.steady_head_at_m(MID_X) + heads[1][grid], atol=1e-9)
    np.testing.assert_allclose(sim.head_m(t), rig.steady_head_m + heads[0][grid], atol=1e-9)
    np.testing.assert_allclose(sim.flow_m3_s(t), rig.steady_flow_m3_s + q[grid], atol=1e-12)
    # the valve's head is the one the single-transducer rig makes (a section at the valve is the valve's head)
    h_valve, _ = transient(tau, rig.with_changes(transducers=()), sim.material)
    np.testing.assert_allclose(heads[0], h_valve, atol=1e-9)
    # the front reaches 0.4 L from the valve (L - x) / a later than the valve
    first = lambda h: tau[np.argmax(h > 1.0)]  # noqa: E731
    assert first(heads[1]) - first(heads[0]) == pytest.approx((rig.pipe.length_m - MID_X) / 353.73, abs=2e-3)


def test_both_simulated_adcs_put_the_mid_transducer_on_input_2(triggered):
    sim, t0 = triggered
    adc = SimModbusADC("pressure_adc", sim, "modbus_adc_sections", buffer_channels=3, autostart=False)
    adc.start_buffer(at=t0 - 1.0)
    regs = np.array(adc._read_ring(0, 3 * 3000, t0 + 0.5)).reshape(-1, 3)  # 3000 samples in: slot j = sample j
    t = adc.t_start + np.arange(regs.shape[0]) / adc.fs
    expect = sim.analog_inputs(t)
    for ch in (0, 1, 2):  # raw counts over 0..24 mA (type 0x0183)
        np.testing.assert_allclose(regs[:, ch] * 24.0 / 65535.0, expect[:, ch], atol=24.0 / 65535.0)


def test_more_transducers_than_inputs_is_one_line_naming_the_rig():
    rig = load_rig("perugia").with_changes(
        transducers=tuple(Section(n, x) for n, x in (("valve", 102.58), ("a", 20.0), ("b", 40.0), ("c", 60.0))))
    with pytest.raises(ConfigError, match="4 transducers; the simulated ADCs have inputs for 3"):
        SimulatedRig(rig, load_material("A"), ManualClock())
