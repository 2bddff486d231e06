"""A valve fired by a digital line, its position measured: the actuator as water-hammer labs have it.

A pneumatic (or spring-return) actuator runs its own stroke when a solenoid pilot or a relay is switched
by a digital output; a potentiometer on the valve stem gives the position on an analog input. velab does
not shape the closure: it fires the line and measures the stroke. The stroke's sigmoid (beta, gamma) is
fitted to the measured position after the run (velab.recording.stroke); the interlock predicts the surge
from the rig's nominal manoeuvre or the last measured one.

    v = FiredValve("valve", line=DaqLine(daq, 0), position=DaqPosition(daq, "valve_position"))
    v.set_manoeuvre(beta, gamma, end)      # the nominal stroke: what the interlock predicts from; nothing sent
    v.arm()                                # checks the line at rest and the valve open: ARMED (host state)
    v.trigger()                            # the line to its firing level: RUNNING
    v.read_status()                        # state from the measured position: RUNNING -> DONE, or FAULT
    v.reset()                              # the line back to rest (reset pulse if wired): the valve reopens

The same verb set and ValveStatus as velab.drivers.valve.ValveActuator, so the recorder drives either.
What the hardware cannot do is said, not faked: a fired stroke cannot be held or stopped part-way
(``hold`` raises DeviceException; ``abort`` of a running stroke lets it run to its end and says so through
``can_stop``). States are the host's view: IDLE / ARMED (armed in velab, nothing on the line), RUNNING (line
fired, position not yet closed), DONE (closed and settled), ABORTED (an armed valve disarmed), FAULT (fired
and no stroke seen within ``stroke_timeout_s``, or the position input failed while the line was fired).

Line and position are injected (``DigitalLine``, ``PositionInput``): a DAQ's own digital output and analog
input (``DaqLine``, ``DaqPosition``: any driver with ``write_digital`` / ``read_digital`` and ``latest`` /
``read_analog``, the DATAQ and LabJack drivers), or another device's.
"""

from __future__ import annotations

import threading
import time
from dataclasses import replace
from typing import Callable, Protocol

from velab.drivers.base import (DeviceError, DeviceException, DeviceFault, DeviceTimeout, Quality, Reading,
                                TriggerRefused, TriggerUnknown)
from velab.drivers.valve import TriggerOutcome, TriggerResult, ValveState, ValveStatus

NO_STROKE = "no stroke seen"  # fault name: fired, and the position did not leave the open end
POSITION_LOST = "position input failed"  # fault name: fired, and the position reading is not a measurement


class DigitalLine(Protocol):
    def set(self, level: bool) -> None: ...
    def get(self) -> bool | None: ...  # the line's state read back, None where the device cannot tell


class PositionInput(Protocol):
    def read(self) -> Reading: ...  # % open, with its quality


class DaqLine:
    """Digital output ``line`` of a DAQ driver (``write_digital(line, level)``, ``read_digital() -> mask``)."""

    def __init__(self, daq, line: int):
        self.daq, self.line = daq, int(line)

    def set(self, level: bool) -> None:
        self.daq.write_digital(self.line, bool(level))

    def get(self) -> bool | None:
        read = getattr(self.daq, "read_digital", None)
        if read is None:
            return None
        state = read()  # a bit mask, or one level per line
        if isinstance(state, (tuple, list)):
            return bool(state[self.line]) if self.line < len(state) else None
        return bool((int(state) >> self.line) & 1)

    def __str__(self) -> str:
        return f"{getattr(self.daq, 'name', 'daq')} digital line {self.line}"


class DaqPosition:
    """The valve position on a DAQ's analog channel: the newest streamed sample while the DAQ streams
    (``latest``), a command-response read otherwise (``read_analog``: a DAQ whose stream is still enabled after
    its reader ended on a fatal error raises that error there, the LabJack's StreamSilent or StreamFault,
    rather than send a read the streaming device refuses)."""

    FIRST_SAMPLE_S = 2.0  # a stream just started: how long its first sample may take

    def __init__(self, daq, channel: str):
        self.daq, self.channel = daq, channel

    def _streaming(self) -> bool:
        s = getattr(self.daq, "streaming", getattr(self.daq, "running", False))
        return bool(s() if callable(s) else s)

    def read(self) -> Reading:
        deadline = time.monotonic() + self.FIRST_SAMPLE_S
        while True:
            r = self.daq.latest(self.channel)
            if r is not None:
                return r
            if not self._streaming():
                return self.daq.read_analog(self.channel)
            if time.monotonic() >= deadline:
                raise DeviceTimeout(f"{self}: no streamed sample within {self.FIRST_SAMPLE_S:g} s",
                                    device=getattr(self.daq, "name", None))
            time.sleep(0.005)

    def __str__(self) -> str:
        return f"{getattr(self.daq, 'name', 'daq')} {self.channel}"


class FiredValve:
    """A valve whose actuator is fired by a digital line; the position measured (see the module's docstring).

    ``fire_level``: the line's level that fires the stroke (True: energise); ``reset_line``: a second line
    pulsed to reopen (a double-acting actuator), else releasing the fire line reopens it (spring return);
    ``closed_pct`` / ``open_pct``: the position thresholds of the stroke's ends; ``stroke_timeout_s``: fired
    and the position still at the open end after this long: FAULT (no stroke seen); ``reopen_timeout_s``:
    how long ``reset`` waits for the valve to reopen."""

    kind = "fired_valve"
    can_hold = False
    reports_own_position = False  # its position is an analog channel (the recorder's redundancy check skips it)

    def __init__(self, name: str, line: DigitalLine, position: PositionInput, *, fire_level: bool = True,
                 reset_line: DigitalLine | None = None, closed_pct: float = 2.0, open_pct: float = 98.0,
                 stroke_timeout_s: float = 3.0, reopen_timeout_s: float = 10.0, reset_pulse_s: float = 0.2,
                 clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep):
        if not 0.0 <= closed_pct < open_pct <= 100.0:
            raise ValueError(f"{name}: closed_pct {closed_pct} and open_pct {open_pct}: need 0 <= closed < open <= 100")
        self.name, self.line, self.position = name, line, position
        self.fire_level, self.reset_line = bool(fire_level), reset_line
        self.closed_pct, self.open_pct = float(closed_pct), float(open_pct)
        self.stroke_timeout_s, self.reopen_timeout_s = float(stroke_timeout_s), float(reopen_timeout_s)
        self.reset_pulse_s = float(reset_pulse_s)
        self.clock, self.sleep = clock, sleep
        self._lock = threading.Lock()  # the host state: the control thread commands, the slow thread reads
        self._state = ValveState.IDLE
        self._faults: tuple[str, ...] = ()
        self._fired_at: float | None = None
        self._left_open = False  # the position has left the open end since the line fired
        self._trigger_count = 0
        self._nominal = (0.0, 0.0, 0.0)

    # -- manoeuvre
    def set_manoeuvre(self, beta_per_s: float, gamma: float, end_position_pct: float = 0.0) -> None:
        """The nominal stroke (what the interlock predicts from): stored, nothing sent; the actuator's stroke
        is its own."""
        self._nominal = (float(beta_per_s), float(gamma), float(end_position_pct))

    def read_manoeuvre(self) -> tuple[float, float, float]:
        return self._nominal

    def identify(self) -> dict:
        return {"model": "valve fired by a digital line", "line": str(self.line), "position": str(self.position),
                "fire_level": "high" if self.fire_level else "low",
                "reset": str(self.reset_line) if self.reset_line is not None else "release of the fire line"}

    # -- commands
    def arm(self, timeout_s: float = 10.0) -> ValveStatus:
        """ARMED when the line is at rest and the valve open and idle; DeviceFault otherwise (nothing moves)."""
        st = self.read_status()
        if st.state is ValveState.FAULT:
            raise DeviceFault(f"{self.name}: in FAULT ({', '.join(st.faults)}): reset it first", device=self.name)
        at_rest = self.line.get()
        if at_rest is not None and at_rest == self.fire_level:
            raise DeviceFault(f"{self.name}: {self.line} is at its firing level before arming", device=self.name)
        if not st.position.quality.is_measurement or st.position.value < self.open_pct:
            raise DeviceFault(f"{self.name}: not open ({st.position.value:.1f} % open, {st.position.quality.value}): "
                              "reset it first", device=self.name)
        with self._lock:
            self._state = ValveState.ARMED
        return self.read_status()

    def trigger(self) -> TriggerOutcome:
        """The fire line to its firing level, once. TriggerRefused-like DeviceException when not ARMED; a
        failed write is the line's own error (the stroke may or may not have started: the position says)."""
        with self._lock:
            if self._state is not ValveState.ARMED:
                raise TriggerRefused(f"{self.name}: cannot fire while {self._state.name} (arm first)", 3,
                                     device=self.name)
        fired_at = self.clock()
        try:
            self.line.set(self.fire_level)
        except DeviceError as exc:
            with self._lock:  # it may have reached the line: watch the position as if fired
                self._fire(fired_at)
            raise TriggerUnknown(f"{self.name}: firing {self.line} failed ({exc}): the valve may be closing",
                                 device=self.name) from exc
        with self._lock:
            self._fire(fired_at)
        return TriggerOutcome(TriggerResult.STARTED)

    def _fire(self, at: float) -> None:
        self._state, self._fired_at, self._left_open = ValveState.RUNNING, at, False
        self._trigger_count += 1

    def hold(self) -> None:
        raise DeviceException(f"{self.name}: a fired stroke cannot be held part-way", 3, device=self.name)

    def can_stop(self) -> bool:
        """False while a fired stroke runs: it runs to its end whatever is commanded."""
        return self._state is not ValveState.RUNNING

    def abort(self) -> None:
        """An armed valve disarmed (nothing was on the line); a running stroke runs to its end (see can_stop)."""
        with self._lock:
            if self._state is ValveState.ARMED:
                self._state = ValveState.ABORTED

    def reset(self) -> None:
        """Reopen: the fire line back to rest (and the reset line pulsed, if wired); IDLE once the position is
        back at the open end, DeviceTimeout after ``reopen_timeout_s``."""
        self.line.set(not self.fire_level)
        if self.reset_line is not None:
            self.reset_line.set(True)
            self.sleep(self.reset_pulse_s)
            self.reset_line.set(False)
        deadline = self.clock() + self.reopen_timeout_s
        while True:
            r = self.position.read()
            if r.quality.is_measurement and r.value >= self.open_pct:
                break
            if self.clock() >= deadline:
                raise DeviceTimeout(f"{self.name}: not reopened after {self.reopen_timeout_s:g} s "
                                    f"({r.value:.1f} % open, {r.quality.value})", device=self.name)
            self.sleep(0.02)
        with self._lock:
            self._state, self._faults, self._fired_at = ValveState.IDLE, (), None

    def close(self) -> None:
        """Nothing of its own to close: the line and the position belong to their DAQ (closed with it)."""

    # -- status
    def read_status(self) -> ValveStatus:
        """The host state advanced by the measured position: RUNNING -> DONE once closed; FAULT when fired and
        no stroke seen within ``stroke_timeout_s`` or the position stopped being a measurement."""
        pos = self.position.read()
        now = self.clock()
        with self._lock:
            if self._state is ValveState.RUNNING:
                since = now - self._fired_at
                if not pos.quality.is_measurement:
                    self._state, self._faults = ValveState.FAULT, (POSITION_LOST,)
                else:
                    if pos.value < self.open_pct:
                        self._left_open = True
                    if pos.value <= self.closed_pct:
                        self._state = ValveState.DONE
                    elif not self._left_open and since > self.stroke_timeout_s:
                        self._state, self._faults = ValveState.FAULT, (NO_STROKE,)
            state, faults = self._state, self._faults
            since = 0.0 if self._fired_at is None else max(0.0, now - self._fired_at)
            count = self._trigger_count
        if state is ValveState.FAULT and pos.quality is Quality.OK:
            pos = replace(pos, quality=Quality.FAULT)
        return ValveStatus(state, pos, faults, since, count)

    def check(self) -> ValveStatus:
        s = self.read_status()
        if s.state is ValveState.FAULT or s.faults:
            raise DeviceFault(f"{self.name}: {', '.join(s.faults) or 'fault'} at {s.position.value:.1f} % open",
                              device=self.name)
        return s

    def wait_for(self, states, timeout_s: float = 5.0, poll_s: float = 0.01, sleep=None, now=None) -> ValveStatus:
        """Poll until the state is one of ``states``; DeviceFault on FAULT, DeviceTimeout after timeout_s."""
        states = {ValveState(s) for s in states}
        sleep, now = sleep or self.sleep, now or self.clock
        deadline = now() + timeout_s
        while True:
            s = self.read_status()
            if s.state in states:
                return s
            if s.state is ValveState.FAULT:
                raise DeviceFault(f"{self.name}: {', '.join(s.faults)} at {s.position.value:.1f} % open",
                                  device=self.name)
            if now() >= deadline:
                raise DeviceTimeout(f"{self.name}: still {s.state.name} after {timeout_s} s (waiting for "
                                    f"{', '.join(x.name for x in states)})", device=self.name)
            sleep(poll_s)
