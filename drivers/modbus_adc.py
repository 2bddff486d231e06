"""Modbus analog-input module for pressure (and valve-position feedback), TCP or RTU.

Two modes, one class (profile ``configs/devices/modbus_adc.toml``):

* **polled** (slow monitoring, ADAM-6017 style): ``read_channels()`` reads the AI raw
  values (0..65535 over the channel's range) and the per-channel status words, and
  returns one Reading per channel in engineering units, quality from the status
  bits (over/under range, burn-out, ADC failure) and the loop calibration.
* **buffered** (the high-rate path): the module samples on its own clock into a
  ring buffer; ``read_buffer()`` reads the sample counter and the new samples in
  blocks of <= 125 registers, timestamps them t0 + i/fs, never invents samples and
  counts what it could not read (overrun) as lost.

Raw counts -> signal (mA) by the channel's range -> engineering value by the
transducer's ``LoopCalibration`` (4-20 mA over 0..6 bar, zero offset) -> head with
``pressure_to_head_m``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from velab.drivers.base import DeviceReset, LoopCalibration, ProfileError, Quality, Reading, pressure_to_head_m
from velab.drivers.blocks import (  # noqa: F401 - QUALITY_CODES re-exported
    QUALITY_CODES,
    SampleBlock,
    StuckDetector,
    signal_quality,
    worst_quality,
)
from velab.drivers.modbus import MAX_READ_REGISTERS
from velab.drivers.modbus_device import ModbusDevice, RangeError

# per-channel status bits (ADAM-6017 style) and what they mean for a sample
STATUS_FAULT_BITS = (1 << 0) | (1 << 7) | (1 << 9)  # UART timeout, ADC failed, calibration error
STATUS_BURNOUT, STATUS_OVER, STATUS_UNDER = 1 << 3, 1 << 1, 1 << 2


@dataclass(frozen=True)
class Channel:
    index: int
    name: str
    type_code: int
    range_lo: float  # signal at raw 0
    range_hi: float  # signal at raw 65535
    calibration: LoopCalibration

    def signal(self, raw):
        return self.range_lo + (self.range_hi - self.range_lo) * np.asarray(raw, dtype=float) / 65535.0


@dataclass
class BufferStats:
    samples: int = 0
    lost: int = 0
    overruns: int = 0
    polls: int = 0
    gaps: list = field(default_factory=list)  # (first lost index, count)


class ModbusADC(ModbusDevice):
    kind = "modbus_adc"
    default_profile = "modbus_adc"

    def __init__(self, bus, profile=None, *, channels: dict | None = None, density_kg_m3: float = 998.2, **kw):
        super().__init__(bus, profile, **kw)
        p = self.profile
        self.density_kg_m3 = density_kg_m3
        pol = p.section("polled")
        self.n_ai = int(pol["channels"])
        self.ai_address = int(pol["ai_address"])
        self.status_address = int(pol["status_address"])
        self.status_bits = {int(k): v for k, v in pol.get("status_bits", {}).items()}
        # a live transducer's noise moves the last bits: unchanged raw counts mean a stuck sensor
        self.stale_after_s = float(pol.get("stale_after_s", 2.0))
        self.stale_samples = int(buf_cfg.get("stale_samples", 200)) if (buf_cfg := p.sections.get("buffer")) else 200
        self._last_raw: dict[int, tuple[int, float]] = {}
        self._stuck = StuckDetector(self.stale_samples)
        buf = p.section("buffer")
        self.ring_address = int(buf["ring_address"])
        self.ring_registers = int(buf["ring_registers"])
        ranges = {int(k, 0): v for k, v in p.section("ranges").items()}
        merged = {k: dict(v) for k, v in p.section("channels").items()}
        for k, v in (channels or {}).items():
            merged.setdefault(k, {}).update(v)
        self.channels: list[Channel] = []
        for i in range(self.n_ai):
            c = merged.get(f"ch{i}")
            if c is None:
                continue
            code = int(c.get("type_code", 0x0180))
            if code not in ranges:
                raise ProfileError(f"{p.path}: [channels.ch{i}] type_code {code:#06x} not in [ranges]")
            try:
                cal = LoopCalibration(float(c["signal_lo"]), float(c["signal_hi"]), float(c["value_lo"]),
                                      float(c["value_hi"]), units=str(c.get("units", "")),
                                      signal_units=ranges[code].get("units", "mA"),
                                      zero_offset=float(c.get("zero_offset", 0.0)),
                                      open_loop_below=3.6 if ranges[code].get("units", "mA") == "mA" else None,
                                      range_margin=float(c.get("range_margin", 0.0)))
            except KeyError as exc:
                raise ProfileError(f"{p.path}: [channels.ch{i}] missing key {exc.args[0]}") from None
            self.channels.append(Channel(i, str(c.get("name", f"ch{i}")), code, float(ranges[code]["lo"]),
                                         float(ranges[code]["hi"]), cal))
        self.stats = BufferStats()
        self._next: int | None = None
        self._fs: float | None = None
        self._nch: int | None = None
        self._cap: int | None = None
        self._t0_dev = 0.0
        self._t0_host: float | None = None
        self._last_counter = 0

    def channel(self, name_or_index) -> Channel:
        for c in self.channels:
            if c.name == name_or_index or c.index == name_or_index:
                return c
        raise KeyError(f"{self.name}: no channel {name_or_index!r} (have {[c.name for c in self.channels]})")

    # ------------------------------------------------------------ polled mode
    def read_channels(self) -> dict[str, Reading]:
        """Every configured channel, in engineering units, with quality from status bits and range."""
        n = max(c.index for c in self.channels) + 1
        raw = self._bus_read("holding", self.ai_address, n)
        status = self._bus_read("holding", self.status_address, 2 * n)
        ts = self.clock()
        out = {}
        for c in self.channels:
            bits = (status[2 * c.index] << 16) | status[2 * c.index + 1]
            signal = float(c.signal(raw[c.index]))
            q = self._status_quality(bits, c, signal)
            last = self._last_raw.get(c.index)
            if last is None or last[0] != raw[c.index]:
                self._last_raw[c.index] = (raw[c.index], ts)
            elif q is Quality.OK and ts - last[1] > self.stale_after_s:
                q = Quality.STALE
            out[c.name] = Reading(c.calibration.value(signal), c.calibration.units, ts, q, raw=raw[c.index])
        return out

    def _status_quality(self, bits: int, c: Channel, signal: float) -> Quality:
        """Status bits first (a set bit the map does not know is a FAULT, never ignored), then
        the loop calibration (NE43: open loop, sensor fault, over/under range)."""
        known = STATUS_FAULT_BITS | STATUS_BURNOUT | STATUS_OVER | STATUS_UNDER
        if bits & STATUS_FAULT_BITS or bits & ~known:
            return Quality.FAULT
        if bits & STATUS_BURNOUT:
            return Quality.OPEN_LOOP
        q = c.calibration.quality(signal)
        if q is not Quality.OK:
            return q
        if bits & STATUS_OVER:
            return Quality.OVER_RANGE
        if bits & STATUS_UNDER:
            return Quality.UNDER_RANGE
        return q

    def status_names(self, bits: int) -> list[str]:
        return [n for b, n in sorted(self.status_bits.items()) if bits >> b & 1]

    def read_pressure(self, channel="pressure") -> Reading:
        return self.read_channels()[self.channel(channel).name]

    def read_head(self, channel="pressure") -> Reading:
        p = self.read_pressure(channel)
        return Reading(pressure_to_head_m(p.value, self.density_kg_m3), "m", p.timestamp_s, p.quality, raw=p.raw)

    # ------------------------------------------------------------ buffered mode
    def configure_buffer(self, sample_rate_hz: int | None = None, n_channels: int | None = None) -> None:
        """Set rate and channel count (the module must be stopped: stop_buffer first)."""
        if sample_rate_hz is not None:
            self.write_value("sample_rate", int(sample_rate_hz))
        if n_channels is not None:
            if n_channels > len(self.channels):
                raise RangeError(f"{self.name}: {n_channels} buffered channels but only {len(self.channels)} configured")
            self.write_value("buffer_channels", int(n_channels))

    def start_buffer(self) -> None:
        """(Re)start the module's acquisition: the counter restarts at 0; read from sample 0."""
        self.write_value("acquisition_control", 1)
        self._attach(from_start=True)

    def stop_buffer(self) -> None:
        self.write_value("acquisition_control", 0)

    def attach_buffer(self) -> None:
        """Follow an acquisition already running: read from the current counter on."""
        self._attach(from_start=False)

    def _attach(self, from_start: bool) -> None:
        p = self.profile
        c = p.reg("sample_counter")
        regs = self._bus_read("holding", c.address, 12)  # 1000..1011: counter..t0
        get = lambda name: p.reg(name).to_value(regs[p.reg(name).address - c.address:][: p.reg(name).count])  # noqa: E731
        counter = int(get("sample_counter"))
        self._fs = float(get("sample_rate"))
        self._nch = int(get("buffer_channels"))
        self._cap = int(get("buffer_capacity"))
        self._t0_dev = float(get("t0"))
        if not (self._fs > 0 and 1 <= self._nch <= len(self.channels) and self._cap >= 1):
            msg = f"module reports rate {self._fs} Hz, {self._nch} channels, capacity {self._cap}"
            self._fs = None
            raise self._implausible(msg)
        self._t0_host = self.clock() - counter / self._fs
        self._next = 0 if from_start else counter
        self._last_counter = counter
        self.stats = BufferStats()
        self._stuck.reset()

    @property
    def sample_rate_hz(self) -> float | None:
        return self._fs

    def _counter(self) -> int:
        """The module's sample counter; it never goes backwards unless the module restarted."""
        c = int(self.read_value("sample_counter"))
        if c < self._last_counter:
            self._next = None  # re-attach explicitly (start_buffer / attach_buffer)
            raise DeviceReset(f"{self.name}: sample counter went back from {self._last_counter} to {c} "
                              f"(module restarted): samples since are not continuous", device=self.name)
        self._last_counter = c
        return c

    def read_buffer(self, max_samples: int | None = None) -> SampleBlock:
        """Everything new since the last call (or up to max_samples), never invented, losses counted."""
        if self._next is None:
            self.attach_buffer()
        fs, nch, cap = self._fs, self._nch, self._cap
        self.stats.polls += 1
        counter = self._counter()
        start = self._next
        lost = 0
        margin = max(1, cap // 20)  # samples the device may write while we read
        if counter - start > cap - margin:
            lost = counter - (cap - margin) - start
            self.stats.overruns += 1
            start += lost
        end = counter if max_samples is None else min(counter, start + max_samples)
        n = max(0, end - start)
        raw = np.zeros((n, nch), dtype=np.uint16)
        per_block = MAX_READ_REGISTERS // nch
        k = start
        while k < end:
            slot = k % cap
            m = min(per_block, end - k, cap - slot)
            regs = self._bus_read("holding", self.ring_address + slot * nch, m * nch)
            raw[k - start:k - start + m] = np.asarray(regs, dtype=np.uint16).reshape(m, nch)
            k += m
        if n:
            # samples whose ring slot was overwritten while we read are dropped, not returned
            after = self._counter()
            oldest_valid = after - cap
            if oldest_valid > start:
                drop = min(n, oldest_valid - start)
                raw = raw[drop:]
                lost += drop
                start += drop
                n -= drop
                self.stats.overruns += 1
        if lost:
            self.stats.gaps.append((self._next, lost))
        self.stats.lost += lost
        self.stats.samples += n
        self._next = start + n
        return self._block(start, raw, lost)

    def _block(self, first: int, raw: np.ndarray, lost: int) -> SampleBlock:
        nch, fs = raw.shape[1], self._fs
        chans = self.channels[:nch]
        signal = np.empty(raw.shape)
        values = np.empty(raw.shape)
        quality = np.zeros(raw.shape, dtype=np.uint8)
        for j, c in enumerate(chans):
            s = c.signal(raw[:, j])
            signal[:, j] = s
            values[:, j] = c.calibration.value(s)
            # raw 0 / 65535: the module clamped at its range's ends, the true signal is beyond
            quality[:, j] = signal_quality(s, c.calibration, clipped_hi=raw[:, j] == 65535, clipped_lo=raw[:, j] == 0)
            self._stuck.flag(j, raw[:, j], quality[:, j])
        n = raw.shape[0]
        return SampleBlock(
            segment=0, first_index=first, rate_hz=fs, host_time_s=self._t0_host + (first + n - 1) / fs,
            raw=raw, signal=signal, values=values, channels=tuple(c.name for c in chans),
            units=tuple(c.calibration.units for c in chans),
            quality=tuple(worst_quality(quality[:, j]) for j in range(nch)), lost_before=lost,
            overrun=lost > 0, density_kg_m3=self.density_kg_m3, sample_quality=quality, device_t0_s=self._t0_dev,
        )

    def head_m(self, block: SampleBlock, channel: str = "pressure") -> np.ndarray:
        return pressure_to_head_m(block.column(channel), self.density_kg_m3)
