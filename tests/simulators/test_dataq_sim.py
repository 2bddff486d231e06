"""The DATAQ driver against the simulated instrument, over a real pty and over a socket: identity, stream
decode and rate, digital output callback, overflow -> named fault, stall -> StreamSilent, dropped byte,
disconnect and reconnection, the sim-bench handle and the pressure-source adapter."""

from __future__ import annotations

import time

import numpy as np
import pytest

from velab.drivers.base import DeviceDisconnected, DeviceFault, StreamSilent
from velab.drivers.bench import BenchDevice
from velab.drivers.dataq import DataqDAQ
from velab.drivers.dataq_bench import open_dataq
from velab.drivers.dataq_profile import default_profile
from velab.drivers.pressure_source import pressure_source
from velab.simulators.dataq_device import DataqFaults
from velab.simulators.dataq_sim import DataqSimHandle, DataqSimulator

pytestmark = pytest.mark.timeout(60)


def ramp(t):
    """Input 0: 4 + (t mod 1 s) x 16 mA (a ramp the decode must follow); input 1: 12 mA (3 V through 250 ohm)."""
    t = np.asarray(t, dtype=float)
    return np.column_stack([4.0 + (t % 1.0) * 16.0, np.full(t.size, 12.0), np.full(t.size, 4.0), np.full(t.size, 4.0)])


def steady(t):
    t = np.asarray(t, dtype=float)
    return np.column_stack([np.full(t.size, 8.0), np.full(t.size, 12.0), np.full(t.size, 4.0), np.full(t.size, 4.0)])


@pytest.fixture
def sim_factory():
    sims = []

    def make(model="DI-2108", source=steady, **kw):
        sim = DataqSimulator(model, source, **kw)
        sims.append(sim)
        return sim

    yield make
    for s in sims:
        s.close()


def daq_for(url, model="DI-2108", **kw):
    kw.setdefault("digital_outputs", (0,) if model != "DI-1100" else ())
    kw.setdefault("data_timeout_s", 1.0)
    return DataqDAQ(url, default_profile(model=model, **kw))


def collect(daq, n, timeout=10.0):
    blocks, deadline = [], time.monotonic() + timeout
    while sum(b.n for b in blocks) < n and time.monotonic() < deadline:
        blocks.append(daq.get_block(timeout=3.0))
    return blocks


def wait_for(cond, timeout=5.0):
    deadline = time.monotonic() + timeout
    while not cond() and time.monotonic() < deadline:
        time.sleep(0.01)
    return cond()


@pytest.mark.parametrize("model", ["DI-2108", "DI-1110", "DI-1100"])
def test_pty_identity_stream_and_rate(sim_factory, model):
    sim = sim_factory(model, ramp, serial_no="1234ABCD")
    link = sim.serve_pty()
    with daq_for(link, model) as daq:
        assert daq.identify() == {"manufacturer": "DATAQ", "model": model, "serial": "1234ABCD", "firmware": "1.21"}
        rate = daq.configure(5000.0)
        assert rate == 5000.0 and sim.rate_hz == rate
        daq.start()
        blocks = collect(daq, 1000)
        daq.stop()
    raw = np.concatenate([b.raw for b in blocks])
    assert sum(b.lost_before for b in blocks) == 0
    idx = np.concatenate([b.index for b in blocks])
    assert (np.diff(idx) == 1).all()
    # the ramp at its sample times, quantised by the model's ADC: the decode follows it sample for sample
    sig = np.concatenate([b.signal for b in blocks])
    expect = ramp(idx / rate)[:, 0]
    lsb_ma = 10.0 / (1 << (daq.spec.adc_bits - 1)) / 0.25
    assert np.abs(sig[:, 0] - expect).max() <= lsb_ma
    assert np.allclose(sig[:, 1], 3.0, atol=0.01)  # volts (no shunt in the profile): 12 mA x 250 ohm
    assert raw.dtype == np.int16


def test_socket_digital_output_reaches_the_callback(sim_factory):
    calls = []
    sim = sim_factory(on_digital=lambda line, level, t: calls.append((line, level)))
    url = sim.serve_tcp()
    with daq_for(url) as daq:
        daq.configure(1000.0)
        daq.write_digital(0, True)  # idle: echoed
        assert daq.read_digital() & 1 == 1
        daq.start()
        collect(daq, 50)
        daq.write_digital(0, False)  # scanning: no echo (p.16)
        assert wait_for(lambda: calls[-1:] == [(0, False)])
        assert wait_for(lambda: daq.read_digital() & 1 == 0)  # the stream's digital word follows
        daq.stop()
        daq.configure(1000.0)  # reconfiguring does not send endo again: no pulse on D0
    assert calls == [(0, True), (0, False)]


def test_overflow_is_a_named_fault(sim_factory):
    sim = sim_factory(faults=DataqFaults(overflow_after_scans=300))
    with daq_for(sim.serve_tcp()) as daq:
        daq.configure(2000.0)
        daq.start()
        with pytest.raises(DeviceFault, match="stop 01"):
            collect(daq, 10**6)
        assert sim.stats.overflows == 1
        delivered = daq.stats.scans
    assert 0 < delivered <= 300


def test_stalled_stream_is_stream_silent_within_data_s(sim_factory):
    sim = sim_factory(faults=DataqFaults(stall_after_scans=200))
    with daq_for(sim.serve_tcp(), data_timeout_s=0.5) as daq:
        daq.configure(2000.0)
        daq.start()
        with pytest.raises(StreamSilent):
            collect(daq, 10**6, timeout=20)


def test_dropped_byte_is_detected_and_counted(sim_factory):
    sim = sim_factory(source=ramp, faults=DataqFaults(drop_byte_at_scans=frozenset({500})))
    with daq_for(sim.serve_pty()) as daq:
        daq.configure(5000.0)
        daq.start()
        blocks = collect(daq, 1500)
        daq.stop()
    assert daq.stats.resyncs == 1
    idx = np.concatenate([b.index for b in blocks])
    sig = np.concatenate([b.signal[:, 0] for b in blocks])
    assert np.abs(sig - ramp(idx / 5000.0)[:, 0]).max() < 0.01  # every delivered sample at its true time
    assert sum(b.lost_before for b in blocks) >= 1


def test_disconnect_reconnects_with_a_restarted_segment(sim_factory):
    sim = sim_factory(faults=DataqFaults(disconnect_after_scans=400, reconnect_delay_s=0.1))
    link = sim.serve_pty()
    with daq_for(link, reconnect=True, reconnect_timeout_s=5.0) as daq:
        daq.configure(5000.0)
        daq.start()
        blocks = collect(daq, 1500, timeout=15)
        daq.stop()
        assert daq.stats.reconnects == 1
    restarted = [b for b in blocks if b.restarted]
    assert len(restarted) == 1 and restarted[0].segment == 1 and restarted[0].lost_before > 0


def test_disconnect_without_reconnect_is_device_disconnected(sim_factory):
    sim = sim_factory(faults=DataqFaults(disconnect_after_scans=200))
    with daq_for(sim.serve_tcp(), reconnect=False) as daq:
        daq.configure(2000.0)
        daq.start()
        with pytest.raises(DeviceDisconnected):
            collect(daq, 10**6)


class _Rig:
    clock = None
    schedule = None
    analog_inputs = staticmethod(steady)


def test_sim_bench_handle_and_pressure_source():
    h = DataqSimHandle("pressure_daq", _Rig(), {"kind": "dataq", "model": "DI-2108",
                                                "endpoints": [{"transport": "socket"}, {"transport": "pty"}]}, "127.0.0.1")
    seen = []
    h.on_digital = lambda line, level, t: seen.append((line, level))
    eps = h.start()
    try:
        assert [e.transport for e in eps] == ["socket", "pty"]
        assert eps[0].bench_settings()["url"].startswith("socket://127.0.0.1:")
        assert eps[1].bench_settings() == {"url": eps[1].link}
        daq = open_dataq(BenchDevice("pressure_daq", "dataq", "dataq_di2108", eps[1].bench_settings()))
        try:
            src = pressure_source(daq, "pressure_daq")
            assert src.channels() == ("pressure", "valve_position")
            assert src.configure(1000.0) == 1000.0
            assert src.start() == 1000.0
            got = []
            deadline = time.monotonic() + 10
            while sum(b.n for b in got) < 200 and time.monotonic() < deadline:
                got += src.read_blocks(0.5).blocks
            daq.write_digital(0, True)
            assert wait_for(lambda: seen == [(0, True)])
            src.stop()
            p = np.concatenate([b.column("pressure") for b in got])
            assert np.allclose(p, 1.5e5, rtol=1e-3)  # 8 mA on 0..6 bar
            assert daq.read_analog("pressure").value == pytest.approx(1.5e5, rel=1e-3)
        finally:
            daq.close()
    finally:
        h.stop()
