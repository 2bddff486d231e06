"""Shared by the device-layer tests: the simulated bench on a manual clock, a quick streaming-ADC profile."""

from __future__ import annotations

from velab.drivers.streaming_adc import default_profile
from velab.simulators.bench import SimulatedBench
from velab.simulators.clock import ManualClock


def manual_sim(config: dict):
    """For a module fixture (``yield from manual_sim(CONFIG)``): the bench of ``config`` on a manual clock,
    ephemeral endpoints, stopped at the end."""
    with SimulatedBench(config, clock=ManualClock(), ephemeral=True) as s:
        yield s


def stream_profile(**kw):
    """The default streaming-ADC profile with short timeouts (tests): command and data 1 s, reconnect 5 s."""
    kw.setdefault("command_timeout_s", 1.0)
    kw.setdefault("data_timeout_s", 1.0)
    kw.setdefault("reconnect_timeout_s", 5.0)
    kw.setdefault("poll_s", 0.02)
    return default_profile(**kw)
