"""Butterfly-valve actuator with its own motion controller (velab register map, docs/devices.md).

    v = ValveActuator(open_bus({"transport": "tcp", "host": ..., "port": ..., "unit": 3}))
    v.set_manoeuvre(beta_per_s=32.0, gamma=-5.5, end_position_pct=0.0)   # or set_closure_time(0.137)
    v.arm(); v.trigger()
    v.wait_for({ValveState.DONE}, timeout_s=2.0)
    v.read_status()       # state, position Reading, fault names, time since trigger

The driver refuses nothing about safety (the recorder holds the interlock); it only
validates arguments against the profile's ranges (RangeError, nothing sent). The
actuator itself answers commands it cannot take with a Modbus exception
(DeviceException: 3 not allowed in this state / bad value, 4 in FAULT, 6 busy).
"""

from __future__ import annotations

import enum
import math
import time
from dataclasses import dataclass, replace

from velab.drivers.base import DeviceFault, DeviceTimeout, Quality, Reading
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


@dataclass(frozen=True)
class ValveStatus:
    state: ValveState
    position: Reading  # % open
    faults: tuple[str, ...]
    time_since_trigger_s: float
    trigger_count: int


class ValveActuator(ModbusDevice):
    kind = "valve_actuator"
    default_profile = "valve_actuator"

    # -- manoeuvre
    def set_manoeuvre(self, beta_per_s: float, gamma: float, end_position_pct: float = 0.0) -> None:
        """Q(t) = Q0 / (1 + exp(beta t + gamma)) towards end_position_pct (% open); one write."""
        specs = [self.profile.reg(n) for n in ("beta", "gamma", "end_position")]
        values = (beta_per_s, gamma, end_position_pct)
        for s, v in zip(specs, values):
            try:
                s.check_range(float(v))
            except ValueError as exc:
                raise RangeError(f"{self.name}: {exc}") from None
        if specs[1].address != specs[0].address + 2 or specs[2].address != specs[1].address + 2:
            for s, v in zip(specs, values):
                self.bus.write_registers(s.address, s.to_registers(v), unit=self.unit)
            return
        regs = [w for s, v in zip(specs, values) for w in s.to_registers(float(v))]
        self.bus.write_registers(specs[0].address, regs, unit=self.unit)

    def set_closure_time(self, closure_time_s: float, end_position_pct: float = 0.0, gamma: float = -5.5) -> None:
        """The equivalent 90 % -> 10 % closure time: beta = ln(81) / T."""
        if not closure_time_s > 0:
            raise RangeError(f"{self.name}: closure_time_s must be positive, got {closure_time_s}")
        self.set_manoeuvre(math.log(81.0) / closure_time_s, gamma, end_position_pct)

    def read_manoeuvre(self) -> tuple[float, float, float]:
        b = self.profile.reg("beta")
        regs = self.bus.read_holding(b.address, 6, unit=self.unit)
        return tuple(self.profile.reg(n).to_value(regs[i * 2:i * 2 + 2]) for i, n in enumerate(("beta", "gamma", "end_position")))

    # -- commands
    def command(self, cmd: Command) -> None:
        self.bus.write_registers(self.profile.reg("command").address, [int(cmd)], unit=self.unit)

    def arm(self) -> None:
        self.command(Command.ARM)

    def trigger(self) -> None:
        self.command(Command.TRIGGER)

    def hold(self) -> None:
        self.command(Command.HOLD)

    def abort(self) -> None:
        self.command(Command.ABORT)

    def reset(self) -> None:
        self.command(Command.RESET)

    # -- status
    def read_state(self) -> ValveState:
        return ValveState(int(self.read_value("state")))

    def read_position(self) -> Reading:
        return self.read("position")

    def read_faults(self) -> tuple[str, ...]:
        spec = self.profile.reg("faults")
        return tuple(spec.bit_names(int(self.read_value("faults"))))

    def read_status(self) -> ValveStatus:
        """State, faults, position, time since trigger and trigger count in two block reads."""
        st = self.profile.reg("state")
        head = self.bus.read_holding(st.address, 2, unit=self.unit)  # state, faults
        pos = self.profile.reg("position")
        body = self.bus.read_holding(pos.address, 5, unit=self.unit)  # position, time, count
        ts = self.clock()
        state = ValveState(head[0])
        faults = tuple(self.profile.reg("faults").bit_names(head[1]))
        position = self._reading(pos, body[0:2], ts)
        if state is ValveState.FAULT and position.quality is Quality.OK:
            position = replace(position, quality=Quality.FAULT)
        tst = self.profile.reg("time_since_trigger").to_value(body[2:4])
        return ValveStatus(state, position, faults, float(tst), int(body[4]))

    def check(self) -> ValveStatus:
        """read_status, raising DeviceFault if the actuator reports a fault."""
        s = self.read_status()
        if s.state is ValveState.FAULT or s.faults:
            raise DeviceFault(f"{self.name}: actuator fault ({', '.join(s.faults) or 'no bits'}) "
                              f"at {s.position.value:.1f} % open, state {s.state.name}")
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
                raise DeviceFault(f"{self.name}: actuator went to FAULT ({', '.join(s.faults)}) "
                                  f"at {s.position.value:.1f} % open")
            if now() >= deadline:
                raise DeviceTimeout(f"{self.name}: still {s.state.name} after {timeout_s} s "
                                    f"(waiting for {', '.join(x.name for x in states)})")
            sleep(poll_s)
