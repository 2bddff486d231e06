"""A spot reading of the bench between runs, for the device table: the steady head, the flow and the
valve, read before anything is armed (the operator sees the steady head at Connect, as the arm's
readiness checks will).

``spot_readings(recorder, rate_hz)`` runs on the engine's control thread (``recorder.submit``), so it
never meets one of the engine's own commands on a device: the engine runs its commands one at a time
there, and between runs nothing else talks to the devices (the slow channels poll only during a run).
It reads what the arm's readiness checks read: the actuator's status, the flowmeter, and a short look
at the valve transducer's pressure channel (``spot_heads``, as ``PressureStage.look``). Each device that
does not answer is left out of the answer rather than failing the others.
"""

from __future__ import annotations

import time

from velab.drivers.base import Quality, Reading
from velab.drivers.pressure_source import pressure_source
from velab.recording.types import DEVICE_ERRORS

LOOK_RATE_HZ = 1000.0


def spot_readings(rec, rate_hz: float = LOOK_RATE_HZ) -> dict:
    """{"head": Reading (m), "flow": Reading (m3/s), "valve_position": Reading (%)}, each read now; a device
    that fails is missing (its fault is the engine's to report when a run needs it)."""
    out: dict = {}
    roles, devices = dict(rec.roles), rec.devices
    try:
        st = devices[roles["valve"]].read_status()
        out["valve_position"] = st.position
    except DEVICE_ERRORS + (KeyError,):
        pass
    try:
        out["flow"] = devices[roles["flowmeter"]].read_flow()
    except DEVICE_ERRORS + (KeyError,):
        pass
    try:
        name = roles["pressure"]
        src = pressure_source(devices[name], name, getattr(rec, "clock_scale", 1.0))
        channel = src.channels()[0]
        if channel is not None:
            head, quality = src.spot_heads(rate_hz, (channel,))[channel]
            q = Quality(quality) if quality in {x.value for x in Quality} else Quality.OK
            out["head"] = Reading(float(head), "m", time.time(), q)
    except DEVICE_ERRORS + (KeyError,):
        pass
    return out
