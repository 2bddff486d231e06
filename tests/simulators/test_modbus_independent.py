"""Independent Modbus clients read the simulated devices at the documented addresses.

minimalmodbus (RTU over a real pty) and pyModbusTCP (Modbus TCP) share no code with
velab's client, so they check the simulators' register maps and framing.
"""

import minimalmodbus
import pytest
from pyModbusTCP.client import ModbusClient as PyModbusTCPClient

from sim_helpers import wait_until
from velab.simulators.bench import SimulatedBench
from velab.simulators.clock import ManualClock

CONFIG = {
    "rig": "perugia", "material": "A", "clock": "manual",
    "devices": {
        "valve": {"kind": "valve_actuator", "unit": 3, "endpoints": [{"transport": "tcp"}, {"transport": "rtu-pty"}]},
        "flowmeter": {"kind": "flowmeter", "unit": 2, "endpoints": [{"transport": "rtu-pty"}, {"transport": "tcp"}]},
    },
}


@pytest.fixture(scope="module")
def sim():
    with SimulatedBench(CONFIG, clock=ManualClock(), ephemeral=True) as s:
        s.clock.advance(100.0)
        yield s


def instrument(path, unit):
    inst = minimalmodbus.Instrument(path, unit)
    inst.serial.baudrate = 19200
    # (the register map and framing are checked, not the latency: the simulated devices run in this test's
    # process, which two other suites on a 2-core host held past 0.5 s: an ABORT went unanswered)
    inst.serial.timeout = 2.0
    inst.clear_buffers_before_each_transaction = True
    inst.close_port_after_each_call = False
    return inst


def test_minimalmodbus_reads_flowmeter_over_pty(sim):
    q0 = sim.rig.rig.steady_flow_m3_s
    inst = instrument(sim.endpoint("flowmeter", "rtu-pty").address, 2)
    try:
        assert inst.read_float(3002, functioncode=3) == pytest.approx(q0, rel=0.01)  # float32 m3/s, ABCD
        total = inst.read_float(3014, functioncode=3, number_of_registers=4)  # DOUBLE totaliser 1
        assert total == pytest.approx(q0 * 100.0, rel=0.01)
        assert inst.read_register(602) == 24  # product code: MAG 6000
        assert inst.read_register(3099) == 1  # update rate set: 2 Hz
    finally:
        inst.serial.close()


def test_minimalmodbus_drives_actuator_over_pty(sim):
    inst = instrument(sim.endpoint("valve", "rtu-pty").address, 3)
    try:
        inst.write_float(10, 25.0)  # beta
        inst.write_float(12, -5.0)  # gamma
        assert inst.read_float(10) == 25.0 and sim.rig.manoeuvre[:2] == (25.0, -5.0)
        assert inst.read_register(1) == 0  # IDLE
        inst.write_register(0, 1, functioncode=16)  # ARM: answered at once, ARMED once the profile is ready
        assert wait_until(lambda: inst.read_register(1), 1) == 1
        inst.write_register(0, 4, functioncode=16)  # ABORT
        assert inst.read_register(1) == 5
        assert inst.read_float(20) == pytest.approx(100.0)  # position, % open
        assert inst.read_register(30) == 0x5641
    finally:
        inst.serial.close()
        sim.rig.reset()


def test_pymodbustcp_reads_flowmeter_and_actuator(sim):
    fm_ep = sim.endpoint("flowmeter", "tcp")
    c = PyModbusTCPClient(host="127.0.0.1", port=fm_ep.port, unit_id=2, timeout=1.0, auto_open=True)
    try:
        regs = c.read_holding_registers(3002, 2)
        import struct

        flow = struct.unpack(">f", struct.pack(">HH", *regs))[0]
        assert flow == pytest.approx(sim.rig.rig.steady_flow_m3_s, rel=0.01)
        assert c.read_holding_registers(602, 1) == [24]
    finally:
        c.close()
    v_ep = sim.endpoint("valve", "tcp")
    c = PyModbusTCPClient(host="127.0.0.1", port=v_ep.port, unit_id=3, timeout=1.0, auto_open=True)
    try:
        assert c.read_holding_registers(1, 2) == [0, 0]  # IDLE, no faults
        assert c.write_multiple_registers(0, [1])  # ARM
        assert wait_until(lambda: c.read_holding_registers(1, 1), [1]) == [1]
        assert c.read_holding_registers(99, 1) is None and c.last_except == 2  # undocumented address
    finally:
        c.close()
        sim.rig.reset()
