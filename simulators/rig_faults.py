"""Model-level faults of the simulated rig: what the sensors and the valve do wrong.

Two sources, both applied at the *sample's* time (so a fault starts and ends at its
exact instant, whatever device samples it):

* ``RigFaults`` (``rig.faults``): set directly or from ``[faults.rig]``, from the start;
* the schedule (``rig.schedule``, velab.simulators.schedule): windows of ``device = "rig"``
  faults, e.g. ``{ channel_mA = { 0 = nan } }`` from trigger+1.5 for 0.5 s (a NaN burst).

Scheduled rig faults: ``channel_mA`` {ch: mA} (forced loop current: 2.0 open loop, 22.0
NE43 failure-high, nan), ``stuck_channels`` [ch] (the channel holds its value from the
window's start: a stuck transducer or valve-position feedback), ``flow_nan``,
``flow_value`` (the meter shows this), ``flow_stuck`` (the meter freezes),
``flow_alarm_bits``, ``valve_seize`` (+ ``valve_fault_bits``: the valve stops where it
is and the actuator goes to FAULT; it stays seized until RESET).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

FAULT_FOLLOWING_ERROR = 0x01


@dataclass
class RigFaults:
    """Model-level faults from the start (the protocol-level ones are in simulators.faults.DeviceFaults).

    stuck_channels : analog channel -> time from which it holds its value (stuck sensor)
    channel_mA : analog channel -> forced loop current (out of range: 22.0; open loop: 0.0; NaN)
    flow_nan : the flowmeter reports NaN
    flow_value : the flowmeter reports this value (out of range)
    flow_stuck_at : the flowmeter freezes at its value at this time
    flow_alarm_bits : alarm bits the flowmeter raises (bit0 empty pipe ...)
    valve_fault_after_s : the valve seizes this long after the trigger; state FAULT
    valve_fault_bits : fault bits then reported
    valve_warning_bits : fault bits the actuator reports while it is NOT in FAULT (a drive or supply warning
        during an otherwise normal stroke: the recorder must flag the run, not ignore them)
    """

    stuck_channels: dict = field(default_factory=dict)
    channel_mA: dict = field(default_factory=dict)
    flow_nan: bool = False
    flow_value: float | None = None
    flow_stuck_at: float | None = None
    flow_alarm_bits: int = 0
    valve_fault_after_s: float | None = None
    valve_fault_bits: int = FAULT_FOLLOWING_ERROR
    valve_warning_bits: int = 0

    def clear(self) -> None:
        self.__init__()


def _scheduled(rig, t_lo: float, t_hi: float) -> list[tuple[float, float, dict]]:
    sched = getattr(rig, "schedule", None)
    return [] if sched is None else sched.windows("rig", t_lo, t_hi)


def apply_input_faults(rig, t: np.ndarray, out: np.ndarray) -> None:
    """Overwrite the loop currents ``out`` (n, 4) sampled at ``t`` with the active faults."""
    f = rig.faults
    for ch, t_stuck in list(f.stuck_channels.items()):
        mask = t >= t_stuck
        if mask.any():
            out[mask, ch] = rig.clean_inputs(np.array([float(t_stuck)]))[0, ch]
    for ch, mA in list(f.channel_mA.items()):
        out[:, ch] = mA
    if t.size == 0:
        return
    for t0, t1, fault in _scheduled(rig, float(t.min()), float(t.max())):
        mask = (t >= t0) & (t < t1)
        if not mask.any():
            continue
        for ch in fault.get("stuck_channels", ()):
            out[mask, ch] = rig.clean_inputs(np.array([t0]))[0, ch]
        for ch, mA in fault.get("channel_mA", {}).items():
            out[mask, ch] = mA


@dataclass(frozen=True)
class FlowFaults:
    nan: bool = False
    value: float | None = None
    stuck_at: float | None = None
    alarm_bits: int = 0


def flow_faults_at(rig, t: float) -> FlowFaults:
    """The flowmeter's faults in force at time t (base, then scheduled windows on top)."""
    f = rig.faults
    nan, value, stuck_at, bits = f.flow_nan, f.flow_value, f.flow_stuck_at, f.flow_alarm_bits
    for t0, t1, fault in _scheduled(rig, t, t):
        if not t0 <= t < t1:
            continue
        nan = nan or fault.get("flow_nan", False)
        value = fault.get("flow_value", value)
        if fault.get("flow_stuck"):
            stuck_at = t0 if stuck_at is None else min(stuck_at, t0)
        bits |= fault.get("flow_alarm_bits", 0)
    return FlowFaults(nan, value, stuck_at, bits)


def pending_seize(rig) -> tuple[float, int] | None:
    """At ARM: a scheduled valve seizure anchored at the coming trigger -> (tau after trigger, bits)."""
    sched = getattr(rig, "schedule", None)
    if sched is None:
        return None
    instants = sched.instants
    for e in sched.entries("rig"):
        if not e.fault.get("valve_seize") or e.at.anchor != "trigger":
            continue
        if not e.every and any(t >= e.created_s - 1e-9 for t in instants.times("trigger")):
            continue  # a "once" seizure whose trigger has already come
        return e.at.offset_s, int(e.fault.get("valve_fault_bits", FAULT_FOLLOWING_ERROR))
    return None


def due_seizures(rig, t: float) -> list[tuple[object, float, int]]:
    """Scheduled seizures not anchored at the trigger whose instant has come: (entry, t0, bits)."""
    sched = getattr(rig, "schedule", None)
    if sched is None:
        return []
    out = []
    for e in sched.entries("rig"):
        if not e.fault.get("valve_seize") or e.at.anchor == "trigger":
            continue
        for t0 in e.starts(sched.instants):
            if t0 <= t and math.isfinite(t0):
                out.append((e, t0, int(e.fault.get("valve_fault_bits", FAULT_FOLLOWING_ERROR))))
    return out
