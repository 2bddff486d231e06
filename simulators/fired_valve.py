"""The simulated fired actuator: a pneumatic (or spring-return) valve actuator released by a DAQ's digital line.

It has no protocol of its own: the simulated DAQ whose output line it is wired to calls
``on_digital(line, level, t)`` when the line changes. The actuator is charged (the rig armed with the
actuator's own stroke, ``rig.arm``) from the start and after every reopening; the line at its firing
level fires the stroke after the solenoid's dead time (``rig.trigger(at=t + dead_time_s)``); the line back
at rest reopens the valve (``rig.reset``: the rig's simplification, an instant reopening). The stroke's
shape is the actuator's (``stroke`` in the sim config, default the rig's nominal manoeuvre), never velab's
command: velab measures it on the position channel.

Sim config::

    [devices.valve]
    kind = "fired_valve"
    daq = "daq"              # the simulated DAQ whose digital output drives it
    fire_line = 0
    fire_level = "high"
    dead_time_s = 0.015      # solenoid + pilot delay
    stroke = { beta_per_s = 32.0, gamma = -5.5 }   # optional: the actuator's own sigmoid in position
"""

from __future__ import annotations

import threading
import time

from velab.errors import ConfigError
from velab.simulators.faults import DeviceFaults
from velab.simulators.rig import CommandRefused, ValveState

_KEYS = {"kind", "daq", "fire_line", "fire_level", "dead_time_s", "stroke"}
ARM_WAIT_S = 10.0  # a line fired while the actuator is still charging waits this long for it


class FiredActuatorSim:
    kind = "fired_valve"
    has_endpoints = False  # reached through its DAQ's line: the sim bench gives it no ports

    def __init__(self, name: str, rig, cfg: dict, host: str = "127.0.0.1"):
        unknown = sorted(set(cfg) - _KEYS)
        if unknown:
            raise ConfigError(f"[devices.{name}] {unknown[0]}: unknown key (known: {', '.join(sorted(_KEYS))})")
        if not isinstance(cfg.get("daq"), str):
            raise ConfigError(f"[devices.{name}] daq: missing (the simulated DAQ whose digital line fires it)")
        self.name, self.rig, self.daq = name, rig, cfg["daq"]
        self.fire_line = int(cfg.get("fire_line", 0))
        level = cfg.get("fire_level", "high")
        if level not in ("high", "low"):
            raise ConfigError(f"[devices.{name}] fire_level: must be \"high\" or \"low\", got {level!r}")
        self.fire_level = level == "high"
        self.dead_time_s = float(cfg.get("dead_time_s", 0.015))
        if not 0.0 <= self.dead_time_s <= 1.0:
            raise ConfigError(f"[devices.{name}] dead_time_s: must be in [0, 1] s, got {self.dead_time_s}")
        m = rig.rig.manoeuvre
        stroke = dict(cfg.get("stroke") or {})
        bad = sorted(set(stroke) - {"beta_per_s", "gamma"})
        if bad:
            raise ConfigError(f"[devices.{name}] stroke.{bad[0]}: unknown key (known: beta_per_s, gamma)")
        self.beta = float(stroke.get("beta_per_s", m.beta_per_s))
        self.gamma = float(stroke.get("gamma", m.gamma))
        if not 0.0 < self.beta <= 1e4:
            raise ConfigError(f"[devices.{name}] stroke.beta_per_s: must be in (0, 1e4] 1/s, got {self.beta}")
        self.faults = DeviceFaults()  # (the bench's fault switches apply to every device; none acts here)
        self._lock = threading.Lock()
        self.fired = 0

    # -- the sim bench's handle interface
    def start(self) -> list:
        self._charge(background=False)
        return []  # no endpoint: it is reached through the DAQ's line

    def stop(self) -> None:
        pass

    def _charge(self, background: bool = True) -> None:
        try:
            self.rig.set_manoeuvre(self.beta, self.gamma, 0.0)
            self.rig.arm(background=background)
        except CommandRefused:
            pass  # in FAULT or mid-stroke: charged again when the line reopens it

    # -- the wiring
    def wire(self, handles: dict, path: str = "<sim config>") -> None:
        """Connect to the simulated DAQ named ``daq``: its digital output changes call on_digital."""
        daq = handles.get(self.daq)
        if daq is None or not hasattr(daq, "on_digital") or daq is self:
            have = ", ".join(n for n, h in handles.items() if hasattr(h, "on_digital") and h is not self)
            raise ConfigError(f"{path}: [devices.{self.name}] daq: {self.daq!r} is not a simulated DAQ with digital "
                              f"outputs (have: {have or 'none'})")
        daq.on_digital = self.on_digital

    def bench_device(self):
        """The bench's [devices.X] table that reaches this valve: through its DAQ's line and position channel."""
        from velab.drivers.bench import BenchDevice

        return BenchDevice(self.name, "fired_valve", None,
                           {"daq": self.daq, "fire_line": self.fire_line,
                            "fire_level": "high" if self.fire_level else "low"})

    def on_digital(self, line: int, level: bool, t: float | None = None) -> None:
        """The DAQ's output ``line`` changed to ``level`` at clock time ``t`` (default now)."""
        if int(line) != self.fire_line:
            return
        t = self.rig.clock.now() if t is None else float(t)
        if bool(level) == self.fire_level:
            self._fire(t + self.dead_time_s)
        else:
            with self._lock:
                if self.rig.state() is not ValveState.ARMED:
                    self.rig.reset()  # spring return / the reopening stroke (instant in the rig's model)
                    self._charge()

    def _fire(self, at: float) -> None:
        with self._lock:
            deadline = time.monotonic() + ARM_WAIT_S
            while self.rig.state() is not ValveState.ARMED and time.monotonic() < deadline:
                if self.rig.state() not in (ValveState.IDLE, ValveState.ARMED):
                    return  # already fired (a repeated level) or in FAULT: nothing happens
                time.sleep(0.005)
            try:
                self.rig.trigger(at=max(at, self.rig.clock.now()) if self.rig.state() is ValveState.ARMED else at)
                self.fired += 1
            except CommandRefused:
                pass
