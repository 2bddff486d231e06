"""The LabJack T-series as a bench device: ``[devices.X] kind = "labjack"`` (the integrator registers
``open_labjack`` in velab.drivers.bench; this module imports the bench, never the other way round)::

    [devices.daq]
    kind = "labjack"
    profile = "labjack_t7"          # configs/devices/labjack_t7.toml
    host = "192.168.1.207"          # optional overrides of the profile: host, port, stream_port, unit,
    stream_port = 702               #   timeout_s, retries, data_s, name, density_kg_m3
    [devices.daq.channels.pressure]
    zero_offset = 150.0             # any [channels.NAME] key of the profile
"""

from __future__ import annotations

from dataclasses import replace

from velab.drivers.base import ProfileError
from velab.drivers.labjack import LabJackT
from velab.drivers.labjack_profile import load_profile
from velab.drivers.modbus import BusSettings, open_bus
from velab.tomlschema import Key, Reader, above, within

_KEYS = {
    "transport": Key(str, False, "tcp", choices=("tcp",)), "host": Key(str, False, None),
    "port": Key(int, False, None, within(1, 65535)), "stream_port": Key(int, False, None, within(1, 65535)),
    "unit": Key(int, False, None, within(0, 247)), "timeout_s": Key(float, False, None, above(0, 60, "s")),
    "retries": Key(int, False, None, within(0, 20)), "reconnect": Key(bool, False, True),
    "data_s": Key(float, False, None, above(0, 600, "s")), "name": Key(str, False, None),
    "density_kg_m3": Key(float, False, 998.2, within(100.0, 5000.0, "kg/m3")), "channels": Key(dict, False, None),
}


def open_labjack(dev, connect: bool = True) -> LabJackT:
    """The driver of one bench device (``dev``: a velab.drivers.bench.BenchDevice); ``connect``: open it."""
    where = f"[devices.{dev.name}] "
    k = Reader(None, dev.settings, error=ProfileError).read(dev.settings, where, _KEYS)
    prof = load_profile(dev.profile or "labjack_t7", overrides=k["channels"])
    over = {f: k[key] for key, f in (("host", "host"), ("port", "port"), ("stream_port", "stream_port"),
                                     ("unit", "unit"), ("timeout_s", "command_s"), ("retries", "retries"),
                                     ("data_s", "data_s")) if k[key] is not None}
    prof = replace(prof, **over)
    settings = BusSettings(transport="tcp", host=prof.host, port=prof.port, unit=prof.unit, timeout_s=prof.command_s,
                           retries=prof.retries, reconnect=k["reconnect"])
    name = k["name"] or dev.name
    bus = open_bus(settings, connect=False, name=f"{name} ({settings.endpoint})")
    lj = LabJackT(bus, prof, name=name, density_kg_m3=k["density_kg_m3"])
    if connect:
        lj.open()
    return lj
