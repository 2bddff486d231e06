"""Shared by the device-layer tests: the simulated bench on a manual clock, a quick streaming-ADC profile;
the simulated rig's physics alone (records the fitter did not make)."""

from __future__ import annotations

import time

from velab.drivers.streaming_adc import default_profile
from velab.simulators.bench import SimulatedBench
from velab.simulators.clock import ManualClock


def manual_sim(config: dict):
    """For a module fixture (``yield from manual_sim(CONFIG)``): the bench of ``config`` on a manual clock,
    ephemeral endpoints, stopped at the end."""
    with SimulatedBench(config, clock=ManualClock(), ephemeral=True) as s:
        yield s


def rig_physics(rig, material: str):
    """The simulated rig's physics alone, no device and no noise: a SimulatedRig on a manual clock, armed with
    the rig's manoeuvre (MOC, the rig's friction and valve laws) -- ``trigger(at=...)`` it, then sample
    ``head_m(t)`` and ``valve_position(t)``."""
    from velab.config import load_material
    from velab.simulators.rig import SimulatedRig

    sim = SimulatedRig(rig, load_material(material), ManualClock(), pressure_noise_fs=0.0, position_noise_pct=0.0)
    sim.arm()
    return sim


def stream_profile(**kw):
    """The default streaming-ADC profile with short timeouts (tests): command and data 1 s, reconnect 5 s."""
    kw.setdefault("command_timeout_s", 1.0)
    kw.setdefault("data_timeout_s", 1.0)
    kw.setdefault("reconnect_timeout_s", 5.0)
    kw.setdefault("poll_s", 0.02)
    return default_profile(**kw)


def wait_until(read, want, timeout_s: float = 10.0):
    """Poll ``read()`` (e.g. the actuator's state register, as an independent client would) until it returns
    ``want``; its last value otherwise (the caller's assertion names it). The simulated actuator answers ARM at
    once and reports ARMED once its transient is computed (a fraction of a second, seconds on a loaded host)."""
    deadline = time.monotonic() + timeout_s
    got = read()
    while got != want and time.monotonic() < deadline:
        time.sleep(0.01)
        got = read()
    return got
