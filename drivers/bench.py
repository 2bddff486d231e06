"""Bench configurations: which devices velab talks to, how, and with which profile.

``benches/<name>.toml`` along the config search path (:mod:`velab.configpath`), or any path::

    name = "simulated rig"
    simulate = "default"            # optional: sim config that ``--simulate`` starts in-process

    [devices.pressure_adc]
    kind = "modbus_adc"             # driver registry key (velab.drivers.bench.DRIVERS)
    profile = "modbus_adc"          # configs/devices/<profile>.toml
    transport = "tcp"               # "tcp" (host, port) or "rtu" (port = path | socket://host:port)
    host = "127.0.0.1"
    port = 15020
    unit = 1
    timeout_s = 0.5
    retries = 2
    reconnect = true
    # driver options: word_order = "CDAB", [devices.X.channels.ch0] zero_offset = 150.0 ...

    [recorder]                      # optional: which device plays which role in `velab record`
    pressure_source = "streaming_adc"   # device name (kind streaming_adc or modbus_adc)
    valve = "valve"
    flowmeter = "flowmeter"

    [recorder.transducers]          # optional: the rig's other transducers -> the pressure source's channels
    mid = "pressure_2"              # (the valve's transducer: the source's first pressure channel, unless named)

``open_device(bench.devices["flowmeter"])`` builds the bus and the driver. The built-in kinds
(Modbus ADC, flowmeter, valve actuator, streaming ADC) are registered here; other kinds can be
added with ``register_driver``.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from typing import Callable

from velab.configpath import config_stem, load_config
from velab.drivers.base import ProfileError
from velab.drivers.dataq_bench import open_dataq
from velab.drivers.fired_valve_bench import open_fired_valve
from velab.drivers.labjack_bench import open_labjack
from velab.drivers.flowmeter import Flowmeter
from velab.drivers.modbus import BusSettings, open_bus
from velab.drivers.modbus_adc import ModbusADC
from velab.drivers.profile import load_profile
from velab.drivers.sadc_bench import open_streaming_adc
from velab.drivers.valve import ValveActuator
from velab.tomlschema import Key, Reader, above, within

RECORDER_ROLES = ("pressure_source", "valve", "flowmeter")
TRANSDUCERS = "transducers"  # [recorder.transducers]: transducer name (the rig's) -> the pressure source's channel


@dataclass(frozen=True)
class BenchDevice:
    name: str
    kind: str
    profile: str | None
    settings: dict = field(default_factory=dict)  # everything else of the [devices.X] table


@dataclass(frozen=True)
class Bench:
    name: str
    devices: dict
    simulate: str | None = None
    path: str = ""
    recorder: dict = field(default_factory=dict)  # the [recorder] table: roles (pressure_source ...)

    @classmethod
    def from_dict(cls, d: dict, path: str = "<bench>") -> "Bench":
        devs = d.get("devices")
        if not isinstance(devs, dict) or not devs:
            raise ProfileError(f"{path}: [devices]: missing or empty")
        out = {}
        r = Reader(path, d, error=ProfileError)
        for name, t in devs.items():
            where = f"[devices.{name}]"
            if not isinstance(t, dict):
                raise r.fail(where, f"must be a table, got {type(t).__name__}")
            t = dict(t)
            kind = r.get(t, where, "kind", str)
            profile = r.get(t, where, "profile", str, None)
            t.pop("kind")
            t.pop("profile", None)
            out[name] = BenchDevice(name, kind, profile, t)
        rec = read_recorder(r, d.get("recorder") or {}, tuple(out))
        simulate = r.get(d, "", "simulate", str, None)
        name = r.get(d, "", "name", str, config_stem(path))
        return cls(name, out, simulate, str(path), dict(rec))

    @property
    def transducer_channels(self) -> dict[str, str]:
        """The ``[recorder.transducers]`` table: transducer name -> the pressure source's channel ({} if none)."""
        return dict(self.recorder.get(TRANSDUCERS) or {})

    def to_dict(self) -> dict:
        d = {"name": self.name, "devices": {}}
        if self.simulate:
            d["simulate"] = self.simulate
        if self.recorder:
            d["recorder"] = dict(self.recorder)
        for n, dev in self.devices.items():
            d["devices"][n] = {"kind": dev.kind, **({"profile": dev.profile} if dev.profile else {}), **dev.settings}
        return d

    def to_toml(self) -> str:
        """This bench as a bench-config TOML text (for a file ``velab record --config`` reads)."""
        d = self.to_dict()
        lines = [f"{k} = {_toml_value(v)}" for k, v in d.items() if not isinstance(v, dict)]
        if d.get("recorder"):
            lines += _toml_table("recorder", d["recorder"])
        for name, t in d["devices"].items():
            lines += _toml_table(f"devices.{name}", t)
        return "\n".join(lines) + "\n"

    def of_kind(self, kind: str) -> list[BenchDevice]:
        return [d for d in self.devices.values() if d.kind == kind]


def read_recorder(r: Reader, rec, devices: tuple[str, ...]) -> dict:
    """A ``[recorder]`` table (a bench's, or a sim config's for the bench it serves), checked: the roles name
    ``devices``; armed_timeout_s disarms an armed rig left alone; ``[recorder.transducers]`` the channel map."""
    if not isinstance(rec, dict):
        raise r.fail("[recorder]", f"must be a table, got {type(rec).__name__}")
    spec = {role: Key(str, False, None, choices=devices) for role in RECORDER_ROLES}
    spec["armed_timeout_s"] = Key(float, False, None, above(0, 86400, "s"))
    spec[TRANSDUCERS] = Key(dict, False, None)
    rec = {k: v for k, v in r.read(rec, "[recorder] ", spec).items() if v is not None}
    if TRANSDUCERS in rec:
        rec[TRANSDUCERS] = _channel_map(r, rec[TRANSDUCERS])
    return rec


def _channel_map(r: Reader, table: dict) -> dict[str, str]:
    """``[recorder.transducers]``: every value a channel name (a string); names checked against the rig and the
    pressure source where the recorder knows both (velab.recording.transducers)."""
    for name, channel in table.items():
        r.get(table, f"[recorder.{TRANSDUCERS}] ", name, str,
              check=lambda v: None if v.strip() else "must name a channel of the pressure source")
    return {str(k): str(v) for k, v in table.items()}


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a JSON string is a valid TOML basic string
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise ValueError(f"cannot write {v!r} to TOML")


def _toml_table(name: str, t: dict) -> list[str]:
    out = ["", f"[{name}]"] + [f"{k} = {_toml_value(v)}" for k, v in t.items() if not isinstance(v, dict)]
    for k, v in t.items():
        if isinstance(v, dict):
            out += _toml_table(f"{name}.{k}", v)
    return out


def load_bench(name_or_path: str | os.PathLike) -> Bench:
    """A bench by short name (``benches/<name>.toml`` along the config search path) or by path."""
    path, doc = load_config("benches", name_or_path, error=ProfileError)
    return Bench.from_dict(doc, str(path))


# ------------------------------------------------------------------ driver registry

DRIVERS: dict[str, Callable[[BenchDevice, bool], object]] = {}
_OPTION_KEYS = ("word_order", "channels", "density_kg_m3", "name")


PEER_KINDS: set[str] = set()  # kinds whose factory takes the bench's other devices (a valve fired by a DAQ's line)


def register_driver(kind: str, factory: Callable[[BenchDevice, bool], object], *, peers: bool = False) -> None:
    """factory(device, connect) -> driver instance; ``peers``: factory(device, connect, peers), where
    ``peers(name)`` is the driver of another bench device (opened once and shared)."""
    DRIVERS[kind] = factory
    if peers:
        PEER_KINDS.add(kind)
    else:
        PEER_KINDS.discard(kind)


def _modbus_factory(cls):
    def make(dev: BenchDevice, connect: bool = True):
        profile = load_profile(dev.profile or cls.default_profile)
        conn = {k: v for k, v in dev.settings.items() if k not in _OPTION_KEYS}
        conn.setdefault("unit", profile.default_unit)
        settings = BusSettings.from_dict(conn, f"[devices.{dev.name}]")
        if settings.extra:
            raise ProfileError(f"[devices.{dev.name}]: unknown key {sorted(settings.extra)[0]!r}")
        bus = open_bus(settings, connect=connect, name=f"{dev.name} ({settings.endpoint})")
        opts = {k: v for k, v in dev.settings.items() if k in _OPTION_KEYS}
        r = Reader(None, opts, error=ProfileError)
        where = f"[devices.{dev.name}] "
        r.get(opts, where, "word_order", str, None, choices=("ABCD", "CDAB", "BADC", "DCBA"))
        r.get(opts, where, "name", str, None)
        r.get(opts, where, "density_kg_m3", float, None, check=within(100.0, 5000.0, "kg/m3"))
        r.get(opts, where, "channels", dict, None)
        opts.setdefault("name", dev.name)
        return cls(bus, profile, unit=settings.unit, **opts)

    return make


def open_device(dev: BenchDevice, connect: bool = True, peers: Callable[[str], object] | None = None):
    """Build the driver for one bench device (and connect its transport). ``peers(name)``: the driver of another
    device of the bench, for the kinds built on one (PEER_KINDS: a valve fired by a DAQ's digital line)."""
    try:
        factory = DRIVERS[dev.kind]
    except KeyError:
        raise ProfileError(f"[devices.{dev.name}] kind: unknown device kind {dev.kind!r} "
                           f"(known: {', '.join(sorted(DRIVERS))})") from None
    if dev.kind in PEER_KINDS:
        return factory(dev, connect, peers)
    return factory(dev, connect)


for _cls in (ModbusADC, Flowmeter, ValveActuator):
    register_driver(_cls.kind, _modbus_factory(_cls))
register_driver("streaming_adc", open_streaming_adc)
register_driver("dataq", open_dataq)
register_driver("labjack", open_labjack)
register_driver("fired_valve", open_fired_valve, peers=True)
