"""Butterfly-valve actuator with its own motion controller (velab register map, docs/devices.md).

    v = ValveActuator(open_bus({"transport": "tcp", "host": ..., "port": ..., "unit": 3}))
    v.set_manoeuvre(beta_per_s=32.0, gamma=-5.5, end_position_pct=0.0)   # or set_closure_time(0.137)
    v.arm(); v.trigger()                   # arm() returns once the actuator reports ARMED
    v.wait_for({ValveState.DONE}, timeout_s=2.0)
    v.read_status()       # state, position Reading, fault names, time since trigger

The driver refuses nothing about safety (the recorder holds the interlock); it only
validates arguments against the profile's ranges (RangeError, nothing sent). The
actuator itself answers commands it cannot take with a Modbus exception
(DeviceException: 3 not allowed in this state / bad value, 4 in FAULT, 6 busy).

Commands are never repeated blindly after a lost reply: the state is read back
first (``trigger()`` -> TriggerOutcome, TriggerNotStarted or TriggerUnknown).
"""

from __future__ import annotations

import enum
import math
import time
from dataclasses import dataclass, replace

from velab.drivers.base import (
    DeviceDisconnected,
    DeviceError,
    DeviceException,
    DeviceFault,
    DeviceTimeout,
    ProtocolError,
    Quality,
    Reading,
    TriggerNotStarted,
    TriggerRefused,
    TriggerUnknown,
)
from velab.drivers.modbus_device import ModbusDevice, RangeError

# the state codes and commands are those of configs/devices/valve_actuator.toml

class ValveState(enum.IntEnum):
    IDLE = 0
    ARMED = 1
    RUNNING = 2
    DONE = 3
    HOLDING = 4
    ABORTED = 5
    FAULT = 6


class Command(enum.IntEnum):
    ARM = 1
    TRIGGER = 2
    HOLD = 3
    ABORT = 4
    RESET = 5


class TriggerResult(str, enum.Enum):
    STARTED = "started"
    NOT_STARTED = "not_started"  # raised as TriggerNotStarted
    UNKNOWN = "unknown"  # raised as TriggerUnknown


@dataclass(frozen=True)
class ValveStatus:
    state: ValveState
    position: Reading  # % open
    faults: tuple[str, ...]
    time_since_trigger_s: float
    trigger_count: int


@dataclass(frozen=True)
class TriggerOutcome:
    """A trigger that started: ``readback`` is True when its reply was lost and the state read
    back said it started (``status``: that read-back; ``lost_reply``: what happened to the reply)."""

    result: TriggerResult
    readback: bool = False
    status: ValveStatus | None = None
    lost_reply: DeviceError | None = None

    @property
    def started(self) -> bool:
        return self.result is TriggerResult.STARTED


class ValveActuator(ModbusDevice):
    kind = "valve_actuator"
    default_profile = "valve_actuator"
    _last_trigger_count: int | None = None  # from the last status read: did a trigger start?

    # -- manoeuvre
    def set_manoeuvre(self, beta_per_s: float, gamma: float, end_position_pct: float = 0.0) -> None:
        """The sigmoid the actuator moves the valve along, in position (% open): p(t) = end + (100 - end) /
        (1 + exp(beta t + gamma)) towards end_position_pct; one write. The flow then follows the valve's
        law (velab.valvelaw): with a butterfly it falls later and faster than p(t)."""
        specs = [self.profile.reg(n) for n in ("beta", "gamma", "end_position")]
        values = (beta_per_s, gamma, end_position_pct)
        for s, v in zip(specs, values):
            try:
                s.check_range(float(v))
            except ValueError as exc:
                raise RangeError(f"{self.name}: {exc}", device=self.name) from None
        if specs[1].address != specs[0].address + 2 or specs[2].address != specs[1].address + 2:
            for s, v in zip(specs, values):
                self._write_regs(s.address, s.to_registers(v))
            return
        regs = [w for s, v in zip(specs, values) for w in s.to_registers(float(v))]
        self._write_regs(specs[0].address, regs)

    def set_closure_time(self, closure_time_s: float, end_position_pct: float = 0.0, gamma: float = -5.5) -> None:
        """The equivalent 90 % -> 10 % closure time of the position: beta = ln(81) / T."""
        if not closure_time_s > 0:
            raise RangeError(f"{self.name}: closure_time_s must be positive, got {closure_time_s}", device=self.name)
        self.set_manoeuvre(math.log(81.0) / closure_time_s, gamma, end_position_pct)

    def read_manoeuvre(self) -> tuple[float, float, float]:
        b = self.profile.reg("beta")
        regs = self._bus_read("holding", b.address, 6)
        return tuple(self.profile.reg(n).to_value(regs[i * 2:i * 2 + 2]) for i, n in enumerate(("beta", "gamma", "end_position")))

    # -- commands
    def command(self, cmd: Command) -> None:
        """Write one command. It is never repeated blindly: after a lost reply (timeout or a
        rejected reply) the state is read back; if the command took effect that is success,
        if it clearly did not the command is sent again (up to the bus's retries). If the
        read-back fails too (after its own retries) the actuator is not answering: the lost
        reply's error is raised at once (more attempts would only multiply the timeouts)."""
        if cmd is Command.TRIGGER:
            self.trigger()
            return
        address = self.profile.reg("command").address
        attempts = 1 + int(getattr(self.bus, "retries", 2))
        for attempt in range(attempts):
            try:
                self._write_regs(address, [int(cmd)], retries=0)
                return
            except (DeviceTimeout, ProtocolError, DeviceDisconnected) as exc:
                lost = exc
            try:
                st = self.read_status()
            except DeviceError as exc:
                raise lost.again(f"{lost}; state not read back either: {exc}") from exc
            if st.state in _REACHED[cmd]:
                return
        raise lost

    def arm(self, timeout_s: float = 10.0) -> ValveStatus:
        """ARM, then wait until the actuator reports ARMED: its controller prepares the profile after the
        command's reply (IDLE meanwhile). DeviceFault if it goes to FAULT, DeviceTimeout after timeout_s."""
        self.command(Command.ARM)
        return self.wait_for({ValveState.ARMED}, timeout_s=timeout_s)

    def trigger(self) -> TriggerOutcome:
        """Start the armed manoeuvre: TRIGGER is sent once, never retried blindly.

        Reply received: STARTED. Modbus exception (not ARMED, FAULT): TriggerRefused
        (a TriggerNotStarted and a DeviceException, ``.code``). Reply lost (timeout, bad CRC, garbled, connection dropped): the valve
        state is read back: the trigger count went up (or the valve left ARMED and its
        time since trigger fits) -> STARTED (``readback=True``); still ARMED with the same
        count, and again one reply timeout later -> TriggerNotStarted (the valve stays ARMED:
        abort() it or trigger again);
        read-back failed -> TriggerUnknown (the valve may be closing).
        """
        address = self.profile.reg("command").address
        count_before = self._last_trigger_count
        sent_at = time.monotonic()
        try:
            self._write_regs(address, [int(Command.TRIGGER)], retries=0)
            if count_before is not None:
                self._last_trigger_count = (count_before + 1) & 0xFFFF
            return TriggerOutcome(TriggerResult.STARTED, readback=False)
        except DeviceException as exc:
            raise TriggerRefused(f"{self.name}: TRIGGER refused: {exc}", exc.code, device=self.name) from exc
        except (DeviceTimeout, ProtocolError, DeviceDisconnected) as exc:
            lost = exc
        st = self._read_back(lost)
        started = self._started_since(st, count_before, time.monotonic() - sent_at)
        if started is False:
            # The TRIGGER may still be on its way: over TCP the client reconnects after a timeout, and the
            # old connection's request can run after the read-back on the new one (a loaded host did
            # this). Once a reply time has passed without it, "not started" holds.
            time.sleep(self.bus.timeout_s)
            st = self._read_back(lost)
            started = self._started_since(st, count_before, time.monotonic() - sent_at)
        if started is True:
            return TriggerOutcome(TriggerResult.STARTED, readback=True, status=st, lost_reply=lost)
        if started is False:
            err = TriggerNotStarted(f"{self.name}: TRIGGER reply lost ({lost}); read back: not started "
                                    f"(state {st.state.name}, trigger count {st.trigger_count})", device=self.name)
            err.status = st
            raise err from lost
        raise TriggerUnknown(f"{self.name}: TRIGGER reply lost ({lost}); read back state {st.state.name} does not "
                             f"tell whether this trigger started it", device=self.name) from lost

    def _read_back(self, lost: DeviceError) -> ValveStatus:
        """The status after a lost TRIGGER reply; TriggerUnknown if it cannot be read."""
        try:
            return self._reread_once(self.read_status)
        except DeviceError as exc:
            raise TriggerUnknown(f"{self.name}: TRIGGER reply lost ({lost}) and the state could not be read back "
                                 f"({exc}): the valve may be moving", device=self.name) from exc

    @staticmethod
    def _started_since(st: ValveStatus, before: int | None, elapsed_s: float) -> bool | None:
        if before is not None:
            return st.trigger_count != before
        if st.state is ValveState.ARMED:
            return False
        if st.state in (ValveState.RUNNING, ValveState.DONE, ValveState.HOLDING, ValveState.FAULT) \
                and st.time_since_trigger_s <= elapsed_s + 1.0:
            return True
        return None

    def hold(self) -> None:
        self.command(Command.HOLD)

    def abort(self) -> None:
        self.command(Command.ABORT)

    def reset(self) -> None:
        self.command(Command.RESET)

    # -- status
    def _state(self, code: int) -> ValveState:
        try:
            return ValveState(code)
        except ValueError:
            raise self._implausible(f"unknown state code {code} (known: "
                                    f"{', '.join(f'{s.value} {s.name}' for s in ValveState)})") from None

    def read_state(self) -> ValveState:
        return self._reread_once(lambda: self._state(int(self.read_value("state"))))

    def read_position(self) -> Reading:
        return self.read("position")

    def read_faults(self) -> tuple[str, ...]:
        spec = self.profile.reg("faults")
        return tuple(spec.bit_names(int(self.read_value("faults"))))

    def read_status(self) -> ValveStatus:
        """State, faults, position, time since trigger and trigger count in two block reads (the state
        once more when a trigger fell between them: a still state with a time since trigger).

        Checked: an unknown state code or an impossible time since trigger is an
        ImplausibleReply (after one re-read); unknown fault bits are reported as
        "bit N", never dropped; a NaN position is NAN, a position outside 0..100 % is
        OVER/UNDER_RANGE, and in FAULT the position's quality is FAULT.
        """
        return self._reread_once(self._read_status_once)

    def _read_status_once(self) -> ValveStatus:
        st = self.profile.reg("state")
        head = self._bus_read("holding", st.address, 2)  # state, faults
        state = self._state(head[0])
        pos = self.profile.reg("position")
        body = self._bus_read("holding", pos.address, 5)  # position, time, count
        ts = self.clock()
        faults = tuple(self.profile.reg("faults").bit_names(head[1]))
        position = self._reading(pos, body[0:2], ts)
        if state is ValveState.FAULT and position.quality is Quality.OK:
            position = replace(position, quality=Quality.FAULT)
        tst = float(self.profile.reg("time_since_trigger").to_value(body[2:4]))
        if not (tst >= 0.0 and math.isfinite(tst)):
            raise self._implausible(f"time since trigger {tst} s")
        if state in (ValveState.IDLE, ValveState.ARMED) and tst > 0.0:
            # a TRIGGER (from another connection) fell between the two reads: the state is older than the
            # position ("ARMED" at 37 % open, 0.19 s into the stroke). The state read again is not older
            # than the position, so the reply is one instant of the actuator's, or later
            again = self._bus_read("holding", st.address, 2)
            state, faults = self._state(again[0]), tuple(self.profile.reg("faults").bit_names(again[1]))
            if state is ValveState.FAULT and position.quality is Quality.OK:
                position = replace(position, quality=Quality.FAULT)
        status = ValveStatus(state, position, faults, tst, int(body[4]))
        self._last_trigger_count = status.trigger_count
        return status

    def check(self) -> ValveStatus:
        """read_status, raising DeviceFault if the actuator reports a fault."""
        s = self.read_status()
        if s.state is ValveState.FAULT or s.faults:
            raise DeviceFault(f"{self.name}: actuator fault ({', '.join(s.faults) or 'no bits'}) "
                              f"at {s.position.value:.1f} % open, state {s.state.name}", device=self.name)
        return s

    def wait_for(self, states, timeout_s: float = 5.0, poll_s: float = 0.01, sleep=time.sleep,
                 now=time.monotonic) -> ValveStatus:
        """Poll until the state is one of ``states``; DeviceFault on FAULT, DeviceTimeout after timeout_s."""
        states = {ValveState(s) for s in states}
        deadline = now() + timeout_s
        while True:
            s = self.read_status()
            if s.state in states:
                return s
            if s.state is ValveState.FAULT:
                raise DeviceFault(f"{self.name}: actuator went to FAULT ({', '.join(s.faults) or 'no bits'}) "
                                  f"at {s.position.value:.1f} % open", device=self.name)
            if now() >= deadline:
                raise DeviceTimeout(f"{self.name}: still {s.state.name} after {timeout_s} s "
                                    f"(waiting for {', '.join(x.name for x in states)})", device=self.name)
            sleep(poll_s)


# the states in which a (non-trigger) command has taken effect, for the read-back after a lost reply
_REACHED = {
    Command.ARM: {ValveState.ARMED},
    Command.HOLD: {ValveState.HOLDING, ValveState.DONE, ValveState.FAULT},
    Command.ABORT: {ValveState.ABORTED},
    Command.RESET: {ValveState.IDLE},
}
