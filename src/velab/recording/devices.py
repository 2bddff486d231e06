"""The bench's devices for a run: roles, connection, identities, profile contents, readiness.

Roles come from the bench's ``[recorder]`` table (``pressure_source``, ``valve``,
``flowmeter``; ``armed_timeout_s`` is the bench's armed timeout; ``[recorder.transducers]`` the
channel of each transducer, velab.recording.transducers) or, without it, the first device of each kind. Readiness (nothing moves): the actuator open and idle, the steady flow
within tolerance and not frozen, the steady head in range and plausible.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from velab.drivers.base import DeviceError, Quality
from velab.drivers.valve import ValveState
from velab.recording.types import DeviceFailure, RunRefused, failed_how

log = logging.getLogger(__name__)
ROLE_KINDS = {"pressure": ("dataq", "labjack", "streaming_adc", "modbus_adc"), "valve": ("fired_valve", "valve_actuator"),
              "flowmeter": ("flowmeter",)}
RECORDER_KEYS = {"pressure_source", "valve", "flowmeter", "armed_timeout_s", "transducers"}


def bench_armed_timeout(bench) -> float | None:
    v = (getattr(bench, "recorder", {}) or {}).get("armed_timeout_s")
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
        raise DeviceFailure(f"{bench.path or bench.name}: [recorder] armed_timeout_s must be a positive number of "
                            f"seconds, got {v!r}")
    return float(v)


def resolve_roles(bench) -> dict[str, str]:
    """role -> bench device name; a one-line error naming what is missing."""
    rec = dict(getattr(bench, "recorder", {}) or {})
    unknown = sorted(set(rec) - RECORDER_KEYS)
    where = bench.path or bench.name
    if unknown:
        raise DeviceFailure(f"{where}: [recorder] {unknown[0]}: unknown key (known: {', '.join(sorted(RECORDER_KEYS))})")
    roles = {}
    for role, kinds in ROLE_KINDS.items():
        name = rec.get("pressure_source" if role == "pressure" else role)
        if name is None:
            found = [d for k in kinds for d in bench.of_kind(k)]
            name = found[0].name if found else None
        if name is None or name not in bench.devices:
            raise DeviceFailure(f"bench {bench.name!r}: no {role} device ({' or '.join(kinds)}; "
                                f"or [recorder] {'pressure_source' if role == 'pressure' else role})")
        if bench.devices[name].kind not in kinds:
            raise DeviceFailure(f"bench {bench.name!r}: [recorder] {role} device {name!r} is a "
                                f"{bench.devices[name].kind}, not a {' or '.join(kinds)}")
        roles[role] = name
    return roles


def profile_contents(driver) -> dict:
    """The device profile the driver uses: its path and its whole text (the run carries contents, not paths)."""
    prof = getattr(driver, "profile", None)
    path = getattr(prof, "path", None)
    d = {"path": str(path) if path else None}
    if path and Path(path).is_file():
        try:
            d["toml"] = Path(path).read_text()
        except OSError as exc:
            d["error"] = str(exc)
    return d


def check_valve_open(st) -> None:
    if st.state is ValveState.FAULT or st.faults:
        where = "in FAULT" if st.state is ValveState.FAULT else f"reports faults while {st.state.name}"
        raise RunRefused(f"valve actuator {where} ({', '.join(st.faults) or 'no bits'}): reset it first (reset_valve())")
    if st.state not in (ValveState.IDLE, ValveState.ARMED) or st.position.value < 99.0:
        raise RunRefused(f"valve not open and idle (state {st.state.name}, {st.position.value:.1f} % open): "
                         "reopen it first (velab valve open, Recorder.reset_valve(), the GUI's Reset valve)")


def check_steady_flow(read_flow, sleep, q0: float, tolerance: float, flow_name: str) -> float:
    """Three readings 0.5 s apart (device time): OK, not frozen, mean and spread within tolerance."""
    flows = []
    for i in range(3):
        try:
            r = read_flow()
        except (DeviceError, ValueError, IndexError) as exc:
            raise DeviceFailure(f"{flow_name}: flowmeter {failed_how(exc)}: {exc}") from None
        if r.quality is not Quality.OK:
            raise RunRefused(f"steady flow not ready: flowmeter reading {r.value!r} is {r.quality.value}")
        flows.append(r.value)
        if i < 2:
            sleep(0.5)
    q = float(np.mean(flows))
    if len(set(flows)) == 1 and flows[0] != 0.0:
        # the meter refreshes at 2 Hz with noise: three readings 0.5 s apart never repeat exactly
        raise RunRefused(f"steady flow not ready: the flowmeter reading is frozen at {flows[0] * 1e3:.4f} l/s "
                         "(stuck sensor or no refresh; check the meter)")
    if abs(q - q0) > tolerance * q0:
        raise RunRefused(f"steady flow {q * 1e3:.3f} l/s is not within {tolerance:.0%} of the rig's "
                         f"Q0 = {q0 * 1e3:.3f} l/s (set the downstream valve)")
    if (max(flows) - min(flows)) > tolerance * q0:
        raise RunRefused(f"steady flow is not stable ({min(flows) * 1e3:.3f}..{max(flows) * 1e3:.3f} l/s)")
    return q


def check_steady_head(head: float, quality: str, steady_head_m: float, head_range, ceiling_m: float,
                      transducer: str = "") -> None:
    """A transducer's look before arming: plausible, within ``head_range`` x its steady head and under the
    ceiling. ``transducer``: names one other than the valve's."""
    lo, hi = (f * steady_head_m for f in head_range)
    at = f" at the transducer {transducer}" if transducer else ""
    if quality != "ok" or not math.isfinite(head):
        raise RunRefused(f"pressure not ready: transducer{' ' + transducer if transducer else ''} reading is {quality}")
    if not lo <= head <= hi or head >= ceiling_m:
        raise RunRefused(f"steady head{at} {head:.2f} m is out of range ({lo:.1f}..{min(hi, ceiling_m):.1f} m)")


def reopen_valve(valve, sleep, settle_s: float = 1.0):
    """Reset the actuator (reopens the valve; clears a FAULT) and let the flow settle; -> ValveStatus.

    One code path for the engine's ``reset_valve()`` and ``velab valve open``."""
    st = valve.read_status()
    if st.state is not ValveState.IDLE or st.position.value < 99.0:
        valve.reset()
        st = valve.wait_for({ValveState.IDLE}, timeout_s=5.0)
        sleep(settle_s)
    return st
