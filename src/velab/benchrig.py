"""The rig as a bench has it: MV's inherent characteristic from the valve's device profile.

A valve body's flow characteristic (Cv/Cv_open against position) is a property of the valve, so a lab
keeps it with the valve's device profile (``[valve]`` table of a ``valve_actuator`` profile, keys as
the rig's ``[valve]`` characteristic keys); the rig file may name its own, which then wins
(velab.config.with_valve_profile). The recorder and the simulated rig both take the rig through here,
so a recorded run stores the characteristic it was made with, and where it came from.
"""

from __future__ import annotations

from velab.config import with_valve_profile
from velab.drivers.profile import load_profile
from velab.rig import Rig

VALVE_KIND = "valve_actuator"


def valve_profile_name(devices: dict, role: str | None = None) -> str | None:
    """The profile of the bench's valve actuator: the device named by the recorder's ``valve`` role,
    else the only device of that kind. ``devices``: name -> object with ``kind``/``profile`` attributes
    or a dict with those keys (a bench file's or a sim config's [devices] tables)."""
    def get(dev, key):
        return dev.get(key) if isinstance(dev, dict) else getattr(dev, key, None)

    valves = {name: dev for name, dev in devices.items() if get(dev, "kind") == VALVE_KIND}
    dev = valves.get(role) if role else None
    if dev is None and len(valves) == 1:
        dev = next(iter(valves.values()))
    if dev is None:
        return None
    return get(dev, "profile") or VALVE_KIND  # the actuator driver's default profile


def rig_for_bench(rig: Rig, devices: dict, role: str | None = None) -> Rig:
    """``rig`` with the characteristic of the bench's valve profile (see the module docstring)."""
    name = valve_profile_name(devices, role)
    if name is None:
        return rig
    return with_valve_profile(rig, load_profile(name))
