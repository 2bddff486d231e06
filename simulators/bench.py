"""The whole simulated rig, in-process: one SimulatedRig, every device served on its endpoints.

    with SimulatedBench.from_config("default", ephemeral=True) as sim:
        sim.endpoints              # [Endpoint(device, kind, transport, address, unit), ...]
        bench = sim.bench()        # a velab.drivers.bench.Bench pointing at the live endpoints
        adc = open_device(bench.devices["pressure_adc"])
        sim.rig                    # the SimulatedRig (state, trigger_time, faults)
        sim.faults["flowmeter"]    # DeviceFaults of one device (protocol faults, from now on)
        sim.schedule_fault("pressure_adc", at="trigger+1.5", duration_s=0.5, silent=True)
        sim.set_fault("rig", channel_mA={0: 22.0}); sim.clear_fault("rig")

Sim config (``sim/<name>.toml`` along the config search path, :mod:`velab.configpath`)::

    rig = "perugia"
    material = "A"
    seed = 0
    clock = "realtime"            # or "manual" (tests)
    host = "127.0.0.1"
    [model]                       # SimulatedRig keyword arguments
    pressure_noise_fs = 2e-4
    [devices.<name>]
    kind = "flowmeter"            # a key of SIM_DEVICES
    unit = 2
    endpoints = [{ transport = "rtu-pty", link = "/tmp/velab-sim/flowmeter", baudrate = 19200 },
                 { transport = "rtu-socket", port = 15023 }, { transport = "tcp", port = 15022 }]
    [faults.<device name>] / [faults.rig]   # from the start: see velab.simulators.faults
    [[faults.schedule]]                     # at an instant: see velab.simulators.schedule
    [recorder]                              # optional: the [recorder] table of the bench it serves
    pressure_source = "pressure_adc"        # (velab.drivers.bench: roles, [recorder.transducers])
    [recorder.transducers]                  # a rig with several transducers: each one's ADC channel
    mid = "pressure_2"                      # (the simulated rig wires them: velab.simulators.rig.input_of)

Device kinds are a registry (``register_sim_device``) of factories
``factory(name, rig, cfg: dict, host: str) -> handle`` where the handle has
``start() -> list[Endpoint]``, ``stop()`` and ``faults``; this module registers the built-in
kinds (the Modbus devices and the streaming ADC): it imports them, they never import it.
"""

from __future__ import annotations

import ipaddress
import os
import threading
from pathlib import Path
from typing import Callable

from velab.benchrig import rig_for_bench
from velab.config import load_material, load_rig
from velab.configpath import load_config
from velab.drivers.bench import Bench, BenchDevice, read_recorder
from velab.errors import ConfigError
from velab.simulators.clock import make_clock
from velab.simulators.endpoint import Endpoint
from velab.simulators.faults import FaultPlan
from velab.simulators.modbus_devices import SimFlowmeter, SimModbusADC, SimValveActuator
from velab.simulators.modbus_server import ModbusDeviceServer
from velab.simulators.pty_bridge import PtyPair
from velab.simulators.rig import SimulatedRig
from velab.simulators.schedule import FaultSchedule, Instant, ScheduledFault, fault_family, validate_fault
from velab.simulators.dataq_sim import DataqSimHandle
from velab.simulators.fired_valve import FiredActuatorSim
from velab.simulators.labjack_sim import LabJackSimHandle
from velab.simulators.streaming_adc import StreamingADCSimHandle
from velab.tomlschema import Key, Reader, above, within

__all__ = ["Endpoint", "SIM_DEVICES", "SimulatedBench", "is_loopback_host", "load_sim_config", "register_sim_device"]


def is_loopback_host(host: str) -> bool:
    """A loopback address (127.0.0.0/8, ::1) or "localhost"? Other names are not resolved (no DNS): not loopback."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.split("%", 1)[0]).is_loopback
    except ValueError:
        return False


SIM_DEVICES: dict[str, Callable] = {}


def register_sim_device(kind: str, factory: Callable) -> None:
    """factory(name, rig, cfg, host) -> handle with start() -> list[Endpoint], stop(), faults."""
    SIM_DEVICES[kind] = factory


class ModbusSimHandle:
    """One simulated Modbus device served on one or more endpoints."""

    def __init__(self, name: str, device, endpoints_cfg: list[dict], host: str):
        self.name, self.device, self.host = name, device, host
        self.faults = device.faults
        self.servers: list = []
        self.ptys: list = []
        self._links: list[str] = []
        self._cfg = endpoints_cfg

    def start(self) -> list[Endpoint]:
        eps = []
        for ep in self._cfg:
            tr = ep.get("transport", "tcp")
            baud = int(ep.get("baudrate", 19200))
            if tr == "tcp" or tr == "rtu-socket":
                srv = ModbusDeviceServer(self.device, tr, host=self.host, port=int(ep.get("port", 0)), baudrate=baud,
                                   wire_delay=bool(ep.get("wire_delay", False))).start()
                self.servers.append(srv)
                eps.append(Endpoint(self.name, self.device.kind, tr, srv.endpoint, self.device.unit, srv.port,
                                    baudrate=baud if tr != "tcp" else None))
            elif tr == "rtu-pty":
                pair = PtyPair(baudrate=baud if ep.get("wire_delay", False) else None).start()
                self.ptys.append(pair)
                srv = ModbusDeviceServer(self.device, "rtu", serial_path=pair.device_path, baudrate=baud).start()
                self.servers.append(srv)
                link = ep.get("link")
                if link:
                    Path(link).parent.mkdir(parents=True, exist_ok=True)
                    if os.path.islink(link):
                        os.unlink(link)
                    os.symlink(pair.host_path, link)
                    self._links.append(link)
                eps.append(Endpoint(self.name, self.device.kind, tr, pair.host_path, self.device.unit,
                                    link=link, baudrate=baud))
            else:
                raise ConfigError(f"[devices.{self.name}] endpoints: unknown transport {tr!r} "
                                  f"(tcp, rtu-socket, rtu-pty)")
        return eps

    def stop(self) -> None:
        for s in self.servers:
            s.stop()
        for p in self.ptys:
            p.stop()
        for link in self._links:
            try:
                if os.path.islink(link):
                    os.unlink(link)
            except OSError:
                pass
        self.servers, self.ptys, self._links = [], [], []

    def disconnect(self) -> None:
        for s in self.servers:
            s.disconnect()

    def reconnect(self) -> None:
        for s in self.servers:
            s.reconnect()


_DEVICE_KEYS = {"kind", "profile", "unit", "word_order", "endpoints", "sample_rate_hz", "buffer_channels"}


def _modbus_factory(Cls):
    def make(name, rig, cfg, host):
        unknown = sorted(set(cfg) - _DEVICE_KEYS)
        if unknown:
            raise ConfigError(f"[devices.{name}] {unknown[0]}: unknown key (known: {', '.join(sorted(_DEVICE_KEYS))})")
        kw = {}
        if Cls.kind == "modbus_adc":
            kw = {k: cfg[k] for k in ("sample_rate_hz", "buffer_channels") if k in cfg}
        dev = Cls(name, rig, cfg.get("profile") or Cls.__init__.__defaults__[0], cfg.get("unit"),
                  cfg.get("word_order"), **kw)
        return ModbusSimHandle(name, dev, cfg.get("endpoints") or [{"transport": "tcp", "port": 0}], host)

    return make


for _cls in (SimModbusADC, SimFlowmeter, SimValveActuator):
    register_sim_device(_cls.kind, _modbus_factory(_cls))
register_sim_device("streaming_adc", StreamingADCSimHandle)
register_sim_device("dataq", DataqSimHandle)
register_sim_device("labjack", LabJackSimHandle)
register_sim_device("fired_valve", FiredActuatorSim)


def load_sim_config(name_or_path) -> tuple[Path, dict]:
    """A sim config by short name (``sim/<name>.toml`` along the config search path) or path -> (path, doc)."""
    return load_config("sim", name_or_path)


# SimulatedRig keyword options ([model]) and the keys every device table may have, with their domains;
# each device kind's factory refuses the keys it does not know.
_MODEL = {
    "pressure_noise_fs": Key(float, False, 2e-4, within(0, 1)),
    "position_noise_pct": Key(float, False, 0.02, within(0, 100)),
    "flow_noise_rel": Key(float, False, 2e-3, within(0, 1)),
    "flow_update_s": Key(float, False, 0.5, above(0, 60, "s")),
    "grid_dt_s": Key(float, False, 2e-4, within(1e-6, 0.1, "s")),
    "transient_s": Key(float, False, 32.0, above(0, 3600, "s")),  # (simulators.rig.TRANSIENT_S)
}
_DEVICE_TYPES = {"kind": str, "profile": str, "unit": int, "word_order": str, "endpoints": list,
                 "sample_rate_hz": int, "buffer_channels": int, "realtime": bool, "baudrate": int, "serial_no": str}
_DEVICE_CHECKS = {"unit": within(0, 247), "sample_rate_hz": within(1, 100_000), "buffer_channels": within(1, 8),
                  "baudrate": within(50, 4_000_000)}
_ENDPOINT = {
    "transport": Key(str, False, None),
    "port": Key(int, False, 0, within(0, 65535)),
    "baudrate": Key(int, False, 19200, within(50, 4_000_000)),
    "link": Key(str, False, None),
    "wire_delay": Key(bool, False, False),
}


def check_sim_config(config: dict, path: str = "<sim config>") -> dict:
    """Types and domains of a sim config's keys (one-line ConfigError naming file and key) -> top-level values."""
    r = Reader(path, config)
    top = r.read(config, "", {
        "name": Key(str, False, ""), "description": Key(str, False, ""), "rig": Key(str, False, "perugia"),
        "material": Key(str, False, "A"), "seed": Key(int, False, 0, within(0, 2**32 - 1)),
        "clock": Key(str, False, "realtime"), "host": Key(str, False, "127.0.0.1"),
        "model": Key(dict, False, {}), "devices": Key(dict, False, {}), "faults": Key(dict, False, None),
        "recorder": Key(dict, False, {}),
    })
    top["recorder"] = read_recorder(r, top["recorder"], tuple(top["devices"]))
    top["model"] = {k: v for k, v in r.read(top["model"], "[model] ", _MODEL).items() if k in top["model"]}
    for name, cfg in top["devices"].items():
        where = f"[devices.{name}] "
        if not isinstance(cfg, dict):
            raise r.fail(where, f"must be a table, got {type(cfg).__name__}")
        for key, kind in _DEVICE_TYPES.items():
            if key in cfg:
                r.get(cfg, where, key, kind, check=_DEVICE_CHECKS.get(key))
        for i, ep in enumerate(cfg.get("endpoints", [])):
            r.read(ep, f"{where}endpoints #{i + 1} ", _ENDPOINT)
    faults = top["faults"] or {}
    for name, t in faults.items():
        if name == "schedule":  # [[faults.schedule]]: checked by velab.simulators.schedule
            continue
        if not isinstance(t, dict):
            raise r.fail(f"[faults.{name}]", f"must be a table, got {type(t).__name__}")
    rig_faults = faults.get("rig", {})
    for key in ("stuck_channels", "channel_mA"):
        for ch, v in (r.get(rig_faults, "[faults.rig] ", key, dict, {})).items():
            if not ch.isdigit():
                raise r.fail(f"[faults.rig] {key}.{ch}", "keys must be channel numbers")
            r.get({ch: v}, f"[faults.rig] {key}.", ch, float)
    return top


class SimulatedBench:
    """Start every simulated device of a sim config in-process; a context manager."""

    def __init__(self, config: dict, *, ephemeral: bool = False, clock=None, host: str | None = None,
                 path: str = "<sim config>", allow_remote: bool = False):
        self.config = config
        self.path = path
        top = check_sim_config(config, path)
        self.recorder = top["recorder"]  # the [recorder] table of the bench it serves (bench())
        self.host = host or top["host"]
        if not allow_remote and not is_loopback_host(self.host):
            # the simulated actuator takes valve commands from whoever can reach it
            raise ConfigError(f"{path}: host {self.host!r} is not a loopback address: the simulated rig (valve "
                              f"control included) would be reachable from the network; allow it explicitly "
                              f"(velab sim --allow-remote)")
        try:
            self.clock = clock or make_clock(top["clock"])
        except ValueError as exc:
            raise ConfigError(f"{path}: clock: {exc}") from None
        try:
            rig, material = load_rig(top["rig"]), load_material(top["material"])
        except ConfigError as exc:  # say which sim config named the rig or material
            raise ConfigError(f"{path}: rig/material: {exc}") from None
        # the valve body's characteristic from its device profile, as the recorder takes it (velab.benchrig)
        rig = rig_for_bench(rig, top["devices"] or {})
        try:
            self.rig = SimulatedRig(rig, material, self.clock, seed=top["seed"], **top["model"])
        except ConfigError as exc:
            raise ConfigError(f"{path}: rig: {exc}") from None
        self.instants = self.rig.instants
        self.schedule = FaultSchedule(self.instants)
        self.rig.schedule = self.schedule
        self.handles: dict[str, object] = {}
        self.kinds: dict[str, str] = {"rig": "rig"}
        self._poller: threading.Thread | None = None
        self._poll_stop = threading.Event()
        self._disconnected: set[str] = set()
        self._poll_lock = threading.Lock()
        devices = top["devices"]
        if not devices:
            raise ConfigError(f"{path}: [devices]: no simulated devices")
        for name, cfg in devices.items():
            cfg = dict(cfg)
            kind = cfg.get("kind")
            if name == "rig":
                raise ConfigError(f"{path}: [devices.rig]: the name 'rig' is reserved for the rig's model faults")
            if kind not in SIM_DEVICES:
                raise ConfigError(f"{path}: [devices.{name}] kind: unknown simulated device kind {kind!r} "
                                  f"(known: {', '.join(sorted(SIM_DEVICES))})")
            if ephemeral and getattr(SIM_DEVICES[kind], "has_endpoints", True):
                cfg["endpoints"] = [{**e, "port": 0, "link": None} for e in cfg.get("endpoints", [{"transport": "tcp"}])]
            self.handles[name] = SIM_DEVICES[kind](name, self.rig, cfg, self.host)
            self.kinds[name] = kind
        for h in self.handles.values():  # devices wired to another (a fired actuator to its DAQ's digital line)
            wire = getattr(h, "wire", None)
            if callable(wire):
                wire(self.handles, path)
        self.faults = {n: h.faults for n, h in self.handles.items()}
        self.plan = FaultPlan.from_dict(config.get("faults"), f"{path}: [faults]")
        self.plan.apply(self.rig, self.faults)
        for kw in self.plan.scheduled(self.kinds, f"{path}: [faults]"):
            self.schedule_fault(kw["device"], kw["at"], kw["duration_s"], every=kw["every"], **kw["fault"])
        self.endpoints: list[Endpoint] = []

    @classmethod
    def from_config(cls, name_or_path="default", **kw) -> "SimulatedBench":
        path, doc = load_sim_config(name_or_path)
        return cls(doc, path=str(path), **kw)

    def start(self) -> "SimulatedBench":
        try:
            for h in self.handles.values():
                self.endpoints.extend(h.start())
        except BaseException:
            self.stop()
            raise
        self._poll_stop.clear()
        self._poller = threading.Thread(target=self._poll_loop, name="velab-sim-faults", daemon=True)
        self._poller.start()
        return self

    def stop(self) -> None:
        self._poll_stop.set()
        if self._poller is not None:
            self._poller.join(2.0)
            self._poller = None
        for h in self.handles.values():
            h.stop()

    # ------------------------------------------------------------ faults at run time

    def schedule_fault(self, device: str, at="now", duration_s: float | None = None, *, every: bool = False,
                       **fault):
        """Schedule ``fault`` (names of the device's kind, velab.simulators.schedule.FAULT_KEYS) on
        ``device`` (a simulated device or "rig") at ``at``: "now", "start", "arm", "trigger",
        each optionally "+seconds", or seconds after the start; for ``duration_s`` (None: until
        cleared); ``every``: at every arm/trigger, not only the next. Returns the ScheduledFault
        (pass it to clear_fault). Bad arguments: ConfigError, one line."""
        if device not in self.kinds:
            raise ConfigError(f"schedule_fault: no simulated device {device!r} "
                              f"(have: {', '.join(sorted(self.kinds))})")
        where = f"schedule_fault({device!r})"
        checked = validate_fault(fault, fault_family(self.kinds[device]), where)
        now = self.clock.now()
        instant = Instant.parse(at, f"{where}: at", now=now)
        if duration_s is not None and not (isinstance(duration_s, (int, float)) and duration_s > 0):
            raise ConfigError(f"{where}: duration_s = {duration_s!r}: must be > 0 (None: until cleared)")
        entry = ScheduledFault(device, checked, instant, None if duration_s is None else float(duration_s),
                               bool(every), created_s=now)
        self.schedule.add(entry)
        if self._poller is not None:
            self.poll_faults()
        return entry

    def set_fault(self, device: str, **fault):
        """A fault from now until cleared (``schedule_fault(device, "now", **fault)``)."""
        return self.schedule_fault(device, "now", **fault)

    def clear_fault(self, device: str | None = None, entry=None) -> None:
        """Remove one scheduled fault (``entry``), or every fault of ``device`` (None: of every
        device and the rig), scheduled or set from the start."""
        if entry is not None:
            self.schedule.remove(entry)
        else:
            self.schedule.clear(device)
            for name in ([device] if device is not None else list(self.kinds)):
                if name == "rig":
                    self.rig.faults.clear()
                    continue
                h = self.handles[name]
                if hasattr(h, "clear_faults"):
                    h.clear_faults()
                elif hasattr(h.faults, "clear"):
                    h.faults.clear()
        if self._poller is not None:
            self.poll_faults()

    def poll_faults(self) -> None:
        """Apply the faults that are states, not replies, at the current instant: a Modbus
        device's scheduled disconnect (and reconnect at its end), scheduled valve seizures.
        The poller thread does this every 10 ms; tests on a manual clock may call it."""
        with self._poll_lock:  # the poller thread and a test may both call this
            now = self.clock.now()
            for name, h in self.handles.items():
                if not hasattr(h, "disconnect") or self.kinds[name] == "streaming_adc":
                    continue  # the streaming ADC checks its own disconnect windows frame by frame
                want = bool(self.schedule.merged(name, now).get("disconnect"))
                if want and name not in self._disconnected:
                    self._disconnected.add(name)
                    h.disconnect()
                elif not want and name in self._disconnected:
                    self._disconnected.discard(name)
                    h.reconnect()
            self.rig.apply_due_seizures(now)

    def _poll_loop(self) -> None:
        while not self._poll_stop.wait(0.01):
            try:
                self.poll_faults()
            except Exception:  # noqa: BLE001 - a failed reconnect is retried at the next tick
                pass

    def describe(self) -> dict:
        """Machine-readable: the endpoints and a bench config (``[devices.X]`` tables) reaching them."""
        bench = self.bench()
        return {"config": self.path, "endpoints": [e.to_dict() for e in self.endpoints],
                "bench": bench.to_dict(), "bench_toml": bench.to_toml()}

    def __enter__(self) -> "SimulatedBench":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def endpoint(self, device: str, transport: str | None = None) -> Endpoint:
        for e in self.endpoints:
            if e.device == device and (transport is None or e.transport == transport):
                return e
        raise KeyError(f"no endpoint for {device!r} over {transport or 'any transport'}")

    def bench(self, prefer: tuple[str, ...] | None = None, **device_options):
        """A velab Bench whose devices point at this simulation's live endpoints.

        Each device uses its first endpoint in config order, or the first of ``prefer``
        (e.g. ("rtu-pty", "tcp")) it has; ``device_options[name]`` adds/overrides keys.
        """
        devices = {}
        for name, h in self.handles.items():
            eps = [e for e in self.endpoints if e.device == name]
            if prefer:
                eps.sort(key=lambda e: prefer.index(e.transport) if e.transport in prefer else len(prefer))
            own = getattr(h, "bench_device", None)
            if callable(own):  # reached through another device (a fired valve through its DAQ's line)
                bd = own()
                devices[name] = BenchDevice(name, bd.kind, bd.profile, {**bd.settings, **device_options.get(name, {})})
                continue
            if not eps:
                continue
            dev = getattr(h, "device", None)
            # a Modbus device's profile as the simulator reads it; the streaming ADC's as its table names it
            profile = dev.profile.path if dev is not None else getattr(h, "profile", None)
            own_settings = getattr(h, "bench_settings", None)  # a device reached on several ports (LabJack)
            settings = own_settings() if callable(own_settings) else eps[0].bench_settings()
            if dev is not None and getattr(dev, "profile", None) is not None:
                settings["word_order"] = dev.profile.word_order.value
            settings.update(device_options.get(name, {}))
            devices[name] = BenchDevice(name, eps[0].kind, profile, settings)
        return Bench(f"simulated ({self.path})", devices, path=self.path, recorder=dict(self.recorder))
