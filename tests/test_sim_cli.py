"""`velab sim` and the in-process SimulatedBench API."""

import subprocess
import sys

import pytest

from velab.drivers.bench import load_bench, open_device
from velab.errors import ConfigError
from velab.simulators.bench import SIM_DEVICES, SimulatedBench, register_sim_device


def test_velab_sim_prints_endpoints_and_stops():
    out = subprocess.run([sys.executable, "-m", "velab.cli", "sim", "--ephemeral", "--duration", "0.3"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    for name in ("pressure_adc", "valve", "flowmeter"):
        assert name in out.stdout
    assert "tcp://127.0.0.1:" in out.stdout and "socket://127.0.0.1:" in out.stdout and "/dev/pts/" in out.stdout
    assert "stopped" in out.stderr


def test_default_sim_serves_the_sim_bench_config():
    """velab sim's fixed ports and configs/benches/sim.toml agree: zero set-up for the recorder."""
    try:
        sim = SimulatedBench.from_config("default").start()
    except RuntimeError as exc:  # a fixed port taken on this machine
        pytest.skip(f"fixed ports busy: {exc}")
    try:
        bench = load_bench("sim")
        for name, dev in bench.devices.items():
            drv = open_device(dev)
            try:
                if name == "flowmeter":
                    assert drv.read_flow().value == pytest.approx(3.64e-3, rel=0.02)
                elif name == "valve":
                    assert drv.read_state().name == "IDLE"
                elif dev.kind == "streaming_adc":
                    assert "SADC-4" in drv.identify()
                else:
                    assert drv.read_pressure().ok
            finally:
                drv.close()
    finally:
        sim.stop()


def test_registry_hook_for_other_device_kinds():
    started = []

    class Handle:
        faults = None

        def start(self):
            started.append(True)
            return []

        def stop(self):
            started.append(False)

    register_sim_device("test_kind", lambda name, rig, cfg, host: Handle())
    try:
        cfg = {"rig": "perugia", "material": "A", "devices": {"x": {"kind": "test_kind"}}}
        with SimulatedBench(cfg, ephemeral=True):
            pass
        assert started == [True, False]
    finally:
        del SIM_DEVICES["test_kind"]
    with pytest.raises(ConfigError, match="unknown simulated device kind"):
        SimulatedBench({"devices": {"x": {"kind": "nope"}}})
