"""Slow channels: the valve actuator's status and the flowmeter, polled on their own thread during a run.

Each poll: the actuator's state and position (``valve`` events, NXlogs ``valve_state`` and
``valve_opening``) and the flow (NXlog ``flow``), a ``device`` event with both readings.
An actuator FAULT ends the run (aborted); a valve that does not answer for ``stall_timeout_s``
before the trigger ends it too (failed: it could not be triggered); afterwards, and for the
flowmeter at any time, the pressure recording goes on and the run is marked. Every device call
is bounded by the bus timeout, so ``stop()`` returns within one poll.
"""

from __future__ import annotations

import logging
import threading
import time

from velab.drivers.base import DeviceFault
from velab.drivers.valve import ValveState
from velab.recording.ops import Slow
from velab.recording.types import DEVICE_ERRORS, failed_how

log = logging.getLogger(__name__)
POLL_S = 0.15


def valve_event(device: str, st) -> dict:
    pos = float(st.position.value)
    return {"device": device, "state": st.state.name, "position_pct": pos, "faults": list(st.faults),
            "open": st.state in (ValveState.IDLE, ValveState.ARMED) and pos >= 99.0}


class SlowChannels:
    def __init__(self, valve, valve_name: str, flowmeter, hooks, write, now_axis, triggered, stall_timeout_s: float,
                 on_valve=None, on_flow=None):
        self.valve, self.valve_name, self.flowmeter = valve, valve_name, flowmeter
        self.hooks, self.write, self.now_axis, self.triggered = hooks, write, now_axis, triggered
        self.stall_timeout_s = stall_timeout_s
        self.on_valve = on_valve or (lambda st: None)
        self.on_flow = on_flow or (lambda r: None)  # each flow Reading (the redundancy check's steady flow)
        self._link_lock = threading.Lock()
        self._answering = True  # (under _link_lock: read by the control thread, valve_link())
        self._valve_error = ""  # why the last valve poll failed
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._flow_faults = 0
        self._valve_silent_since: float | None = None
        self._flow_quality_seen: set = set()
        self._valve_held = threading.Event()
        self._fault_bits_seen: set = set()  # fault bits already reported while the actuator was not in FAULT

    def start(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._loop, name="velab-recorder-slow", daemon=True)
        self._thread.start()

    def request_stop(self) -> None:
        self._stop.set()

    def stop(self, timeout: float = 5.0) -> bool:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout)
            return not self._thread.is_alive()
        return True

    def _loop(self) -> None:
        while not self._stop.is_set():
            t0 = time.monotonic()
            try:
                self.poll()
            except Exception as exc:  # noqa: BLE001 - a bug: report, keep the recording going
                log.exception("slow poll")
                self.hooks.fault("recorder", f"slow-channel poll failed: {type(exc).__name__}: {exc}")
            self._stop.wait(max(0.0, POLL_S - (time.monotonic() - t0)))

    def valve_link(self) -> tuple[bool, str]:
        """(the valve answers its polls, why not), from any thread."""
        with self._link_lock:
            return self._answering, self._valve_error

    def _set_link(self, answering: bool, error: str = "") -> bool:
        """Record the last poll's outcome; returns whether the valve answered before it."""
        with self._link_lock:
            before, self._answering = self._answering, answering
            if error:
                self._valve_error = error
            return before

    def hold_valve(self, held: bool) -> None:
        """While held, the polls leave the actuator alone: a command in flight (the trigger and its
        read-back) has the bus to itself instead of queueing behind a poll's timeouts."""
        (self._valve_held.set if held else self._valve_held.clear)()

    def poll(self) -> None:
        readings = {}
        t = self.now_axis()
        epoch = time.time()  # the host instant of this poll, stored with the slow channels (NXlog time)
        if not self._valve_held.is_set():
            self._poll_valve(readings, t, epoch)
        try:
            r = self.flowmeter.read_flow()
            readings["flow"] = r
            self.write(Slow("flow", t, r.value, time.time()))
            self.on_flow(r)
            if r.quality.value != "ok" and r.quality.value not in self._flow_quality_seen:
                self._flow_quality_seen.add(r.quality.value)
                self.hooks.fault("flowmeter", f"flowmeter reading {r.quality.value} at t = {t:.2f} s", "quality",
                                 quality=r.quality.value)
        except DEVICE_ERRORS as exc:  # the pressure recording goes on
            self._flow_faults += 1
            if self._flow_faults in (1, 10, 100):
                self.hooks.fault("flowmeter", f"{exc} (pressure recording continues)", "no_response")
        if readings:
            self.hooks.emit("device", readings)

    def _poll_valve(self, readings: dict, t: float, epoch: float) -> None:
        try:
            st = self.valve.read_status()
            if not self._set_link(True):
                self.hooks.fault("valve", "answers again", "no_response")
            self._valve_silent_since = None
            readings["valve_position"] = st.position
            self.on_valve(st)
            self.hooks.emit("valve", valve_event(self.valve_name, st))
            self.write(Slow("valve_state", t, int(st.state), epoch))
            self.write(Slow("valve_opening", t, st.position.value, epoch))
            if st.state is ValveState.FAULT:
                msg = f"valve actuator FAULT ({', '.join(st.faults) or 'no bits'}) at {st.position.value:.1f} % open"
                self.hooks.fault("valve", msg, "actuator_fault", faults=list(st.faults))
                self.hooks.request_end("aborted", msg)
            elif st.faults and set(st.faults) - self._fault_bits_seen:
                # fault bits outside FAULT: the actuator says something is wrong while it still moves or rests
                # (a drive or supply warning): the run is flagged, never a plain "completed"
                self._fault_bits_seen |= set(st.faults)
                self.hooks.fault("valve", f"actuator reports {', '.join(st.faults)} while {st.state.name} at "
                                          f"{st.position.value:.1f} % open", "actuator_fault", faults=list(st.faults))
        except DeviceFault as exc:
            self.hooks.fault("valve", str(exc), "actuator_fault")
            self.hooks.request_end("aborted", str(exc))
        except DEVICE_ERRORS as exc:
            now = time.monotonic()
            if self._set_link(False, str(exc)):
                self.hooks.fault("valve", f"actuator {failed_how(exc)}: {exc}", "no_response")
                self._valve_silent_since = now
            if not self.triggered() and now - (self._valve_silent_since or now) > self.stall_timeout_s:
                self.hooks.request_end("failed", f"{self.valve_name} (valve): no answer for "
                                                 f"{self.stall_timeout_s:g} s before the trigger: {exc}")
