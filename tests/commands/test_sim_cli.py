"""`velab sim` and the in-process SimulatedBench API."""

import subprocess
import sys

import pytest

from velab.drivers.bench import load_bench, open_device
from velab.errors import ConfigError
from velab.simulators.bench import SIM_DEVICES, SimulatedBench, register_sim_device


def _velab(*argv, timeout=60):
    return subprocess.run([sys.executable, "-m", "velab.cli", *argv], capture_output=True, text=True, timeout=timeout)


def test_velab_sim_prints_endpoints_and_stops():
    out = _velab("sim", "--config", "default", "--ephemeral", "--duration", "0.3", "-v")
    assert out.returncode == 0, out.stderr
    for name in ("pressure_adc", "valve", "flowmeter"):
        assert name in out.stdout
    assert "tcp://127.0.0.1:" in out.stdout and "socket://127.0.0.1:" in out.stdout and "/dev/pts/" in out.stdout
    assert "stopped" in out.stderr


def test_velab_sim_serves_a_bench_of_products_by_default():
    """Without --config: the DATAQ DI-2108 on a pty (as a USB CDC device appears) and a socket, the valve fired
    by its digital line, the SITRANS flowmeter."""
    import json

    out = _velab("sim", "--ephemeral", "--duration", "0.5", "--json")
    assert out.returncode == 0, out.stderr
    doc = json.loads(out.stdout.splitlines()[0])
    kinds = {name: d["kind"] for name, d in doc["bench"]["devices"].items()}
    assert kinds == {"daq": "dataq", "valve": "fired_valve", "flowmeter": "flowmeter"}, kinds
    assert doc["bench"]["devices"]["valve"]["daq"] == "daq"
    addresses = " ".join(e["address"] for e in doc["endpoints"])
    assert "/dev/pts/" in addresses and "socket://127.0.0.1:" in addresses


def test_sim_on_other_loopback_address_is_allowed():
    out = _velab("sim", "--config", "default", "--ephemeral", "--duration", "0.3", "--host", "127.0.0.2")
    assert out.returncode == 0, out.stderr
    assert "tcp://127.0.0.2:" in out.stdout
    assert out.stderr == ""  # loopback: no exposure notice, and nothing but errors on stderr


@pytest.mark.parametrize("host", ["0.0.0.0", "::", "192.0.2.1", "lab-pc.example"])
def test_sim_beyond_loopback_needs_allow_remote(host):
    out = _velab("sim", "--ephemeral", "--duration", "5", "--host", host)
    assert out.returncode == 2
    assert out.stdout == ""  # refused before anything was served
    assert out.stderr.count("\n") == 1 and "not a loopback address" in out.stderr and "--allow-remote" in out.stderr


def test_exposure_notice_names_every_device():
    from velab.commands.sim import exposure_notice

    # constructed, never started: no socket is bound
    sim = SimulatedBench.from_config("default", ephemeral=True, host="0.0.0.0", allow_remote=True)
    text = exposure_notice(sim)
    assert "0.0.0.0" in text and "not a loopback address" in text
    for name in ("valve", "flowmeter", "pressure_adc", "streaming_adc"):
        assert name in text
    assert "valve control" in text
    with pytest.raises(ConfigError, match="not a loopback address"):
        SimulatedBench.from_config("default", ephemeral=True, host="0.0.0.0")


def _endpoint_of(device_cfg: dict, transport: str):
    for e in device_cfg["endpoints"]:
        if e.get("transport", "tcp") == transport:
            return e
    return None


def test_default_sim_and_the_sim_bench_config_agree():
    """velab sim's fixed ports (sim/default.toml) are the ones benches/sim.toml points at, device by
    device; checked on the files, without binding the fixed ports (tests run concurrently)."""
    from velab.simulators.bench import load_sim_config

    _, sim_doc = load_sim_config("default")
    bench = load_bench("sim")
    assert bench.simulate == "default"
    for name, dev in bench.devices.items():
        sim_dev = sim_doc["devices"][name]
        assert sim_dev["kind"] == dev.kind
        if dev.kind == "streaming_adc":
            port = int(dev.settings["url"].rsplit(":", 1)[1])
            assert _endpoint_of(sim_dev, "socket")["port"] == port
            continue
        assert sim_dev["profile"] == dev.profile and sim_dev["unit"] == dev.settings["unit"]
        if dev.settings["transport"] == "tcp":
            assert _endpoint_of(sim_dev, "tcp")["port"] == dev.settings["port"]
            assert dev.settings["host"] == sim_doc["host"]
        else:
            assert dev.settings["port"].startswith("socket://")
            assert _endpoint_of(sim_dev, "rtu-socket")["port"] == int(dev.settings["port"].rsplit(":", 1)[1])
            assert _endpoint_of(sim_dev, "rtu-socket")["baudrate"] == dev.settings["baudrate"]


def test_sim_bench_devices_talk_to_the_running_sim():
    """The bench's drivers (profiles, units, word orders) work against the live simulated rig (ephemeral ports)."""
    with SimulatedBench.from_config("default", ephemeral=True) as sim:
        bench = sim.bench()
        assert set(bench.devices) == set(load_bench("sim").devices)
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
