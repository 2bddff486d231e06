"""The simulated LabJack T7 served on loopback: Modbus TCP (port 502's role) and the stream port (702's role).

    h = LabJackSimHandle("daq", rig, {"shunt_ohm": 249.0}, "127.0.0.1")
    endpoints = h.start()            # [Endpoint(... "tcp" ...), Endpoint(... "labjack-stream" ...)]
    h.bench_settings()               # {"host", "port", "stream_port", "unit"}: the [devices.X] keys reaching it
    h.on_digital = valve.fire        # FIO writes -> (line, level, t)
    h.faults.silent = True           # Modbus faults (DeviceFaults); h.stream_faults.stall = True (stream faults)
    h.disconnect_stream()            # the stream connection drops
    h.stop()

``factory(name, rig, cfg, host)`` for ``velab.simulators.bench.register_sim_device`` (the integrator registers
it). Config keys: ``unit``, ``shunt_ohm`` (one value or four, ohm), ``serial``, ``device_name``, ``port`` and
``stream_port`` (0: ephemeral) or ``endpoints`` ([{transport = "tcp", port}, {transport = "labjack-stream",
port}]); ``model`` = "T7".
"""

from __future__ import annotations

import socket
import threading

from velab.errors import ConfigError
from velab.simulators.endpoint import Endpoint
from velab.simulators.labjack_device import TICK_S, SimLabJackT
from velab.simulators.modbus_server import ModbusDeviceServer

KIND = "labjack"
STREAM_TRANSPORT = "labjack-stream"
_KEYS = {"kind", "model", "unit", "shunt_ohm", "serial", "device_name", "port", "stream_port", "endpoints", "profile"}


class LabJackSimHandle:
    def __init__(self, name: str, rig, cfg: dict | None = None, host: str = "127.0.0.1"):
        cfg = dict(cfg or {})
        unknown = sorted(set(cfg) - _KEYS)
        if unknown:
            raise ConfigError(f"[devices.{name}] {unknown[0]}: unknown key (known: {', '.join(sorted(_KEYS))})")
        if cfg.get("model", "T7") != "T7":
            raise ConfigError(f"[devices.{name}] model: only a simulated T7 exists, got {cfg['model']!r}")
        ports = {"tcp": int(cfg.get("port", 0)), STREAM_TRANSPORT: int(cfg.get("stream_port", 0))}
        for ep in cfg.get("endpoints") or []:
            tr = ep.get("transport", "tcp")
            if tr not in ports:
                raise ConfigError(f"[devices.{name}] endpoints: transport {tr!r} (a LabJack has tcp and "
                                  f"{STREAM_TRANSPORT})")
            ports[tr] = int(ep.get("port", 0))
        self.name, self.host, self.ports = name, host, ports
        shunt = cfg.get("shunt_ohm", 249.0)
        self.lj = SimLabJackT(name, rig, unit=int(cfg.get("unit", 1)), serial=int(cfg.get("serial", 470_012_345)),
                              device_name=str(cfg.get("device_name", f"velab-sim-{name}")), shunt_ohm=shunt)
        self.faults = self.lj.faults
        self.stream_faults = self.lj.stream_faults
        self.profile = cfg.get("profile", "labjack_t7")  # the driver's profile (SimulatedBench.bench names it)
        self.server: ModbusDeviceServer | None = None
        self._listener: socket.socket | None = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.stream_port = 0

    @property
    def on_digital(self):
        return self.lj.on_digital

    @on_digital.setter
    def on_digital(self, callback) -> None:
        self.lj.on_digital = callback

    def start(self) -> list[Endpoint]:
        self._stop.clear()
        self.server = ModbusDeviceServer(self.lj, "tcp", host=self.host, port=self.ports["tcp"]).start()
        self._listener = socket.create_server((self.host, self.ports[STREAM_TRANSPORT]))
        self.stream_port = self._listener.getsockname()[1]
        for target, what in ((self._accept, "accept"), (self._run, "scan")):
            th = threading.Thread(target=target, name=f"velab-sim-{self.name}-{what}", daemon=True)
            th.start()
            self._threads.append(th)
        return [Endpoint(self.name, KIND, "tcp", self.server.endpoint, self.lj.unit, self.server.port),
                Endpoint(self.name, KIND, STREAM_TRANSPORT, f"tcp://{self.host}:{self.stream_port}", None,
                         self.stream_port)]

    def bench_settings(self) -> dict:
        """The [devices.X] keys of velab.drivers.labjack_bench.open_labjack that reach this simulator."""
        return {"host": self.host, "port": self.server.port, "stream_port": self.stream_port, "unit": self.lj.unit}

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._listener.accept()
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            old, self.lj.client = self.lj.client, conn  # the newest 702 connection gets the data
            if old is not None:
                _shut(old)

    def _run(self) -> None:
        while not self._stop.wait(TICK_S):
            self.lj.tick()

    def disconnect_stream(self) -> None:
        """The stream connection drops (cable, switch): the host sees it closed."""
        c, self.lj.client = self.lj.client, None
        if c is not None:
            _shut(c)

    def clear_faults(self) -> None:
        self.faults.clear()
        self.stream_faults.clear()

    def stop(self) -> None:
        self._stop.set()
        if self._listener is not None:
            _shut(self._listener)
            self._listener = None
        self.disconnect_stream()
        for th in self._threads:
            th.join(2.0)
        self._threads = []
        if self.server is not None:
            self.server.stop()
            self.server = None

    def __enter__(self) -> "LabJackSimHandle":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def _shut(sock) -> None:
    for call in (lambda: sock.shutdown(socket.SHUT_RDWR), sock.close):
        try:
            call()
        except OSError:
            pass
