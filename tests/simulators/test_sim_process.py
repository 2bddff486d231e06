"""Real-time faults and process-level faults: ``velab sim --ephemeral --json`` in a subprocess,
frozen (SIGSTOP) and killed (SIGKILL) under live drivers; every driver call ends in a named error
within a bound, and a frozen simulator that resumes is usable again."""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import time
import tomllib

import pytest

from velab.drivers.base import DeviceDisconnected, DeviceException, DeviceTimeout, StreamSilent
from velab.drivers.bench import Bench, load_bench, open_device
from velab.simulators.bench import SimulatedBench
from velab.simulators.clock import RealTimeClock

pytestmark = pytest.mark.timeout(180)


def test_real_time_fault_window_is_consistent_with_the_clock():
    """On real time, every request wholly before the window works, every one wholly inside
    fails with the injected exception, every one wholly after works again."""
    cfg = {"rig": "perugia", "material": "A",
           "devices": {"flowmeter": {"kind": "flowmeter", "endpoints": [{"transport": "tcp"}]}}}
    with SimulatedBench(cfg, clock=RealTimeClock(), ephemeral=True) as sim:
        fm = open_device(sim.bench(flowmeter={"timeout_s": 1.0, "retries": 0}).devices["flowmeter"])
        try:
            entry = sim.schedule_fault("flowmeter", at="now+0.3", duration_s=0.3, exception_code=4)
            (t0, t1), = entry.windows(sim.instants)
            seen = []
            while sim.clock.now() < t1 + 0.3:
                a = sim.clock.now()
                try:
                    fm.read_value("flow")
                    ok = True
                except DeviceException as exc:
                    assert exc.code == 4
                    ok = False
                seen.append((a, sim.clock.now(), ok))
                time.sleep(0.01)
        finally:
            fm.close()
    before = [ok for a, b, ok in seen if b < t0]
    inside = [ok for a, b, ok in seen if a >= t0 and b < t1]
    after = [ok for a, b, ok in seen if a >= t1]
    assert before and all(before)
    assert inside and not any(inside)
    assert after and all(after)


def _spawn_sim():
    p = subprocess.Popen([sys.executable, "-m", "velab.cli", "sim", "--config", "default", "--ephemeral", "--json"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    ready, _, _ = select.select([p.stdout], [], [], 60)
    assert ready, "velab sim printed nothing"
    info = json.loads(p.stdout.readline())
    assert info["pid"] == p.pid
    return p, info


@pytest.fixture
def sim_process():
    p, info = _spawn_sim()
    yield p, info
    if p.poll() is None:
        os.kill(p.pid, signal.SIGCONT)
        p.kill()
    p.wait(30)


def test_sim_json_is_a_bench_config(sim_process, tmp_path):
    p, info = sim_process
    assert {e["device"] for e in info["endpoints"]} >= {"pressure_adc", "valve", "flowmeter", "streaming_adc"}
    path = tmp_path / "bench.toml"
    path.write_text(info["bench_toml"])
    bench = load_bench(path)
    assert tomllib.loads(info["bench_toml"]) == info["bench"] and bench.to_dict() == info["bench"]
    for name in ("valve", "flowmeter"):
        drv = open_device(bench.devices[name])
        try:
            assert drv.read_state().name == "IDLE" if name == "valve" else drv.read_flow().ok
        finally:
            drv.close()


def _drivers(info):
    bench = Bench.from_dict(info["bench"])
    bench.devices["valve"].settings.update(timeout_s=0.3, retries=1)
    bench.devices["streaming_adc"].settings.update(data_s=0.5, reconnect_s=1.0, command_s=0.5)
    valve = open_device(bench.devices["valve"])
    adc = open_device(bench.devices["streaming_adc"])
    adc.configure(1000, ["pressure"], block_samples=10)
    adc.start()
    adc.get_block(timeout=5)
    return valve, adc


def _bounded(fn, exc, limit_s=15.0):
    t0 = time.monotonic()
    with pytest.raises(exc) as ei:
        while True:
            fn()
    assert time.monotonic() - t0 < limit_s, "a dead simulator must be named within seconds"
    return ei.value


def test_frozen_sim_is_named_then_usable_again(sim_process):
    p, info = sim_process
    valve, adc = _drivers(info)
    try:
        os.kill(p.pid, signal.SIGSTOP)
        e = _bounded(valve.read_status, DeviceTimeout)
        assert e.device == "valve" and "no reply" in str(e)
        s = _bounded(lambda: adc.get_block(timeout=5), StreamSilent)
        assert s.reason == "silent" and adc.condition == "failed"
        os.kill(p.pid, signal.SIGCONT)
        assert valve.read_status().state.name == "IDLE"
        adc.close()
        adc.configure(1000, ["pressure"], block_samples=10)
        adc.start()
        assert adc.get_block(timeout=5).n > 0
    finally:
        adc.close()
        valve.close()


def test_killed_sim_is_named_within_seconds(sim_process):
    p, info = sim_process
    valve, adc = _drivers(info)
    try:
        p.kill()
        p.wait(30)
        e = _bounded(valve.read_status, DeviceDisconnected)
        assert e.device == "valve" and e.reason == "disconnected"
        d = _bounded(lambda: adc.get_block(timeout=5), DeviceDisconnected)
        assert "could not reconnect within 1 s" in str(d) and adc.condition == "failed"
    finally:
        adc.close()
        valve.close()
