"""Simulated Modbus devices: register images computed from the one SimulatedRig at request time.

Each class reads the same device profile TOML as its driver (one register map, one
source of truth) and offers what :class:`velab.simulators.modbus_server.ModbusDeviceServer`
needs: ``unit``, ``faults``, ``layout()``, ``read(address, count)``,
``write(address, values) -> exception code | None``.
"""

from __future__ import annotations

import math

import numpy as np

from velab.drivers.profile import Profile, load_profile
from velab.simulators.clock import buffer_scale
from velab.simulators.faults import DeviceFaults
from velab.simulators.rig import CommandRefused, SimulatedRig

ILLEGAL_ADDRESS, ILLEGAL_VALUE, DEVICE_FAILURE, DEVICE_BUSY = 2, 3, 4, 6


def parse_ranges(profile: Profile) -> dict[int, tuple[float, float]]:
    return {int(k, 0): (float(v["lo"]), float(v["hi"])) for k, v in profile.section("ranges").items()}


class SimModbusDevice:
    kind = "modbus"

    def __init__(self, name: str, rig: SimulatedRig, profile: Profile | str, unit: int | None = None,
                 word_order: str | None = None):
        self.name = name
        self.rig = rig
        self.profile = load_profile(profile)
        if word_order:
            self.profile = self.profile.with_word_order(word_order)
        self.unit = self.profile.default_unit if unit is None else unit
        self.faults = DeviceFaults()
        self.image: dict[int, int] = {}

    def layout(self) -> list[tuple[int, int]]:
        raise NotImplementedError

    def put(self, reg_name: str, value) -> None:
        spec = self.profile.reg(reg_name)
        for i, w in enumerate(spec.to_registers(value)):
            self.image[spec.address + i] = w

    def get(self, reg_name: str):
        spec = self.profile.reg(reg_name)
        return spec.to_value([self.image.get(spec.address + i, 0) for i in range(spec.count)])

    def refresh(self, now: float) -> None:
        """Put live values into the image."""

    def read(self, address: int, count: int) -> list[int]:
        self.refresh(self.rig.clock.now())
        return [self.image.get(a, 0) for a in range(address, address + count)]

    def write(self, address: int, values: list[int]) -> int | None:
        return ILLEGAL_ADDRESS


# ------------------------------------------------------------------ flowmeter


class SimFlowmeter(SimModbusDevice):
    """SITRANS F M MAG 6000-style flowmeter: flow, totalisers, 2 Hz refresh, alarm word."""

    kind = "flowmeter"

    def __init__(self, name, rig, profile="sitrans_mag6000", unit=None, word_order=None):
        super().__init__(name, rig, profile, unit, word_order)
        for k, v in {"slave_id": 0x2A, "product_code": 24, "parity_errors": 0, "framing_errors": 0,
                     "crc_errors": 0, "response_timeout": 1000, "response_delay": 0, "update_rate": 1,
                     "totalizer2": 0.0, "totalizer2_f32": 0.0}.items():
            self.put(k, v)
        self.image[503] = self.image[504] = 0
        self.image[2202] = 0

    def layout(self):
        return [(500, 5), (511, 2), (600, 1), (602, 1), (2202, 1), (3002, 24), (3099, 2)]

    def refresh(self, now: float) -> None:
        rig = self.rig
        tu = rig.flowmeter_update_time(now)
        self.put("flow", rig.flowmeter_value(now))
        tot = rig.totalizer_m3(tu)
        self.put("totalizer1", tot)
        self.put("totalizer1_f32", tot)
        self.put("alarms", rig.flow_alarm_bits(now))

    def write(self, address, values):
        if address == self.profile.reg("update_rate").address and len(values) == 1:
            if values[0] != 1:
                return ILLEGAL_VALUE
            self.image[address] = values[0]
            return None
        return ILLEGAL_ADDRESS


# ------------------------------------------------------------------ valve actuator

COMMANDS = {1: "arm", 2: "trigger", 3: "hold", 4: "abort", 5: "reset"}


class SimValveActuator(SimModbusDevice):
    """The valve's motion controller: manoeuvre parameters, commands, position, state, faults."""

    kind = "valve_actuator"

    def __init__(self, name, rig, profile="valve_actuator", unit=None, word_order=None):
        super().__init__(name, rig, profile, unit, word_order)
        beta, gamma, end = rig.manoeuvre
        self.put("beta", beta)
        self.put("gamma", gamma)
        self.put("end_position", end)
        self.put("model_id", 0x5641)
        self.image[0] = 0

    def layout(self):
        return [(0, 3), (10, 6), (20, 5), (30, 1)]

    def refresh(self, now: float) -> None:
        # the whole status block at one instant of the actuator (SimulatedRig.valve_status)
        state, faults, position, since, count = self.rig.valve_status()
        self.put("state", int(state))
        self.put("faults", faults)
        self.put("position", position)
        self.put("time_since_trigger", since)
        self.put("trigger_count", count & 0xFFFF)

    def write(self, address, values):
        p = self.profile
        if address == p.reg("command").address and len(values) == 1:
            name = COMMANDS.get(values[0])
            if name is None:
                return ILLEGAL_VALUE
            try:
                if name == "arm":  # replied at once; ARMED when the controller has its profile
                    self.rig.arm(background=True)
                else:
                    getattr(self.rig, name)()
            except CommandRefused as exc:
                return exc.code
            return None
        first, last = p.reg("beta").address, p.reg("end_position").address + 1
        if first <= address and address + len(values) <= last + 1:
            saved = dict(self.image)
            for i, v in enumerate(values):
                self.image[address + i] = v
            try:
                beta, gamma, end = self.get("beta"), self.get("gamma"), self.get("end_position")
                for n, v in (("beta", beta), ("gamma", gamma), ("end_position", end)):
                    p.reg(n).check_range(v)
                self.rig.set_manoeuvre(beta, gamma, end)
            except ValueError:
                self.image = saved
                return ILLEGAL_VALUE
            except CommandRefused as exc:
                self.image = saved
                return exc.code
            return None
        return ILLEGAL_ADDRESS


# ------------------------------------------------------------------ Modbus ADC


REGISTER_SPACE = 65536  # Modbus holding-register addresses 0..65535


def ring_registers(profile_registers: int, ring_address: int, scale: float) -> int:
    """The simulated ring's size: the profile's times ``scale`` (velab.simulators.clock.buffer_scale) as far as
    the register space allows (from the ring's address to 65535). The real module's ring holds 4 s of 2 channels at
    2 kHz; at the fast clock (12 x) those 4 s were 0.33 s of host time, and a loaded test host lost samples the real
    bench never would. The module reports its capacity (``buffer_capacity``), which the driver reads: any size is
    the protocol's."""
    return min(int(profile_registers * scale), REGISTER_SPACE - ring_address)


class SimModbusADC(SimModbusDevice):
    """ADAM-6017-style AI module with the velab sample buffer, fed by rig.analog_inputs."""

    kind = "modbus_adc"

    STATUS_OVER, STATUS_UNDER, STATUS_BURNOUT, STATUS_ADC_FAILED = 1 << 1, 1 << 2, 1 << 3, 1 << 7

    def __init__(self, name, rig, profile="modbus_adc", unit=None, word_order=None, *,
                 sample_rate_hz: int = 2000, buffer_channels: int = 2, autostart: bool = True):
        super().__init__(name, rig, profile, unit, word_order)
        self.ranges = parse_ranges(self.profile)
        pol = self.profile.section("polled")
        self.n_ai = int(pol["channels"])
        self.ai_addr = int(pol["ai_address"])
        self.status_addr = int(pol["status_address"])
        self.type_addr = int(pol["type_address"])
        self.polled_rate = float(pol.get("sample_rate_hz", 10))
        buf = self.profile.section("buffer")
        self.ring_addr = int(buf["ring_address"])
        self.ring_regs = ring_registers(int(buf["ring_registers"]), self.ring_addr, buffer_scale(rig.clock))
        chans = self.profile.section("channels")
        self.type_codes = [int(chans.get(f"ch{i}", {}).get("type_code", 0x0180)) for i in range(self.n_ai)]
        for i, code in enumerate(self.type_codes):
            self.image[self.type_addr + i] = code
        self.put("module_name", 0x60170000)
        self.fs = int(sample_rate_hz)
        self.nch = int(buffer_channels)
        self.running = False
        self.t_start = 0.0
        self.frozen_count = 0
        if autostart:
            self.start_buffer()

    # -- buffer state
    @property
    def capacity(self) -> int:
        return self.ring_regs // self.nch

    def start_buffer(self, at: float | None = None) -> None:
        self.t_start = self.rig.clock.now() if at is None else at
        self.running = True

    def counter(self, now: float) -> int:
        if not self.running:
            return self.frozen_count
        return max(0, int(math.floor((now - self.t_start) * self.fs + 1e-9)))

    def layout(self):
        return [(self.ai_addr, self.n_ai), (self.status_addr, 2 * self.n_ai), (self.type_addr, self.n_ai),
                (210, 2), (1000, 12), (self.ring_addr, self.ring_regs)]

    # -- conversion
    def to_raw(self, mA: np.ndarray, channels) -> np.ndarray:
        lo = np.array([self.ranges[self.type_codes[c]][0] for c in channels])
        hi = np.array([self.ranges[self.type_codes[c]][1] for c in channels])
        frac = (np.nan_to_num(mA, nan=lo) - lo) / (hi - lo)
        return np.clip(np.round(frac * 65535.0), 0, 65535).astype(np.int64)

    def status_bits(self, mA: float, ch: int) -> int:
        lo, hi = self.ranges[self.type_codes[ch]]
        if math.isnan(mA):
            return self.STATUS_ADC_FAILED
        bits = 0
        margin = 0.005 * (hi - lo)
        if mA > hi + margin:
            bits |= self.STATUS_OVER
        if lo > 0 and mA < lo - margin:
            bits |= self.STATUS_UNDER
            if mA < 3.6:
                bits |= self.STATUS_BURNOUT
        return bits

    # -- register image
    def refresh(self, now: float) -> None:
        c = self.counter(now)
        self.put("sample_counter", c & 0xFFFFFFFF)
        self.put("sample_rate", self.fs)
        self.put("buffer_channels", self.nch)
        self.put("buffer_capacity", self.capacity)
        self.put("buffer_status", 1 if self.running else 0)
        self.put("acquisition_control", 1 if self.running else 0)
        self.put("t0", self.t_start)

    def read(self, address: int, count: int) -> list[int]:
        now = self.rig.clock.now()
        if address >= self.ring_addr:
            return self._read_ring(address - self.ring_addr, count, now)
        if address < self.status_addr + 2 * self.n_ai:  # AI values or status: sample the module
            ts = math.floor(now * self.polled_rate) / self.polled_rate
            mA = self.rig.analog_inputs(np.array([ts]))[0]
            mA = np.concatenate([mA, np.full(max(0, self.n_ai - mA.size), 4.0)])[: self.n_ai]
            raw = self.to_raw(mA, range(self.n_ai))
            for i in range(self.n_ai):
                self.image[self.ai_addr + i] = int(raw[i])
                self.image[self.status_addr + 2 * i] = 0
                self.image[self.status_addr + 2 * i + 1] = self.status_bits(float(mA[i]), i)
        return super().read(address, count)

    def _read_ring(self, offset: int, count: int, now: float) -> list[int]:
        c = self.counter(now)
        cap, n = self.capacity, self.nch
        r = np.arange(offset, offset + count)
        slot, ch = r // n, r % n
        valid = (slot < cap) & (c > 0)
        j = c - 1 - ((c - 1 - slot) % cap)
        valid &= j >= 0
        out = np.zeros(count, dtype=np.int64)
        if valid.any():
            uj, inv = np.unique(j[valid], return_inverse=True)
            mA = self.rig.analog_inputs(self.t_start + uj / self.fs)
            chv = ch[valid]
            vals = mA[inv, chv]
            lo = np.array([self.ranges[self.type_codes[k]][0] for k in range(n)])[chv]
            hi = np.array([self.ranges[self.type_codes[k]][1] for k in range(n)])[chv]
            frac = (np.nan_to_num(vals, nan=0.0) - lo) / (hi - lo)
            out[valid] = np.clip(np.round(frac * 65535.0), 0, 65535)
        return out.tolist()

    def write(self, address, values):
        p = self.profile
        now = self.rig.clock.now()
        if address == p.reg("acquisition_control").address and len(values) == 1:
            if values[0] == 1:
                self.start_buffer(now)
            elif values[0] == 0:
                self.frozen_count = self.counter(now)
                self.running = False
            else:
                return ILLEGAL_VALUE
            return None
        if address == p.reg("sample_rate").address and len(values) == 2:
            fs = p.reg("sample_rate").to_value(values)
            try:
                p.reg("sample_rate").check_range(fs)
            except ValueError:
                return ILLEGAL_VALUE
            if self.running:
                return DEVICE_BUSY
            self.fs = int(fs)
            return None
        if address == p.reg("buffer_channels").address and len(values) == 1:
            if not 1 <= values[0] <= 4:
                return ILLEGAL_VALUE
            if self.running:
                return DEVICE_BUSY
            self.nch = values[0]
            return None
        return ILLEGAL_ADDRESS
