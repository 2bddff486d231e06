"""A simulated LabJack T7: LabJack's registers over Modbus TCP and spontaneous stream packets on a second port.

``SimLabJackT`` is the device (what :class:`velab.simulators.modbus_server.ModbusDeviceServer` serves: ``unit``,
``faults``, ``layout()``, ``read``, ``write``) and its stream engine; ``LabJackSimHandle`` serves it for the sim
bench (``factory(name, rig, cfg, host)``: ``start() -> [Endpoint]``, ``stop()``, ``faults``).

What the device does, from LabJack's documents (velab.drivers.labjack_registers, velab.drivers.labjack_stream):

* inputs: AIN0..3 are the rig's loop currents (``SimulatedRig.analog_inputs(t)``, mA: 0 pressure, 1 valve
  position, 2-3 the other transducers) through ``shunt_ohm`` to volts; AIN# reads volts (command-response,
  refused while a stream runs: datasheet 3.2 "analog inputs cannot be read via command-response while a stream is
  active"); the stream sends the high-speed converter's 16-bit binary through this device's own calibration
  constants, served from its internal flash at 0x3C4000 (INTERNAL_FLASH_READ_POINTER / INTERNAL_FLASH_READ);
* FIO#: a write makes the line an output at that level and calls ``on_digital(line, level, t)``;
* stream: STREAM_ENABLE = 1 checks the configuration (a bad one: a Modbus exception, as the device refuses it),
  then scans are taken at the scan rate on the rig's clock into a FIFO of STREAM_BUFFER_SIZE_BYTES (default 4096,
  the T7's; on a clock K x real time K x as many, the same host time: velab.simulators.clock.buffer_scale), sent as packets of STREAM_SAMPLES_PER_PACKET to the connection on the stream port; a full FIFO
  starts auto-recovery (2940 .. 2941 with the skipped scans and a dummy 0xFFFF scan), or with
  STREAM_AUTORECOVER_DISABLE = 1 ends the stream with STREAM_BUFFER_FULL (2945);
* STREAM_SCANRATE_HZ reads back the actual rate: the scan interval in whole steps of 0.1 us (1, 10, 100 us,
  1 ms for slow rates), as the map's description says.

Stream faults (``stream_faults``): ``hold_s`` (packets held back this long: the FIFO overflows as on a slow
network), ``stall`` (the device stops scanning and sending, the connection stays open), ``scan_overlap`` (the next
packet reports STREAM_SCAN_OVERLAP and the stream stops), ``garble`` (the next packet's header is corrupted);
``disconnect_stream()`` closes the stream connection. Modbus faults: ``faults`` (DeviceFaults) as every
simulated Modbus device.
"""

from __future__ import annotations

import math
import socket
import threading
from dataclasses import dataclass
from typing import Callable

import numpy as np

from velab.drivers import labjack_registers as ljr
from velab.drivers.labjack_stream import DUMMY_SAMPLE, MAX_SAMPLES_PER_PACKET, T7Calibration, encode_packet
from velab.drivers.modbus_types import decode_registers, encode_value
from velab.simulators.clock import buffer_scale
from velab.simulators.faults import DeviceFaults

ILLEGAL_ADDRESS, ILLEGAL_VALUE, DEVICE_FAILURE = 2, 3, 4
N_AIN = 14  # T7: AIN0..AIN13
T7_BUFFER_DEFAULT = 4096  # STREAM_BUFFER_SIZE_BYTES = 0 (the map: "T7 ... Default size is 4096")
T7_MAX_SAMPLE_RATE = 100_000.0
TICK_S = 0.004
# this unit's factory constants: near the nominal ones, not equal, so a host that ignores them reads wrong
SIM_CALIBRATION = T7Calibration(tuple((ps * (1 + 0.002 * (g + 1)), ns * (1 - 0.0015 * (g + 1)), 33523.0 + 17 * g, off)
                                      for g, (ps, ns, _c, off) in enumerate(
                                          [(0.000315805780 / 10 ** g, -0.000315805800 / 10 ** g, 0, -10.586956522)
                                           for g in range(4)])))


def actual_scan_rate(rate_hz: float) -> float:
    """The rate the device runs at: the interval in whole steps of 0.1 us (16-bit count), else 1/10/100 us, 1 ms."""
    for step in (1e-7, 1e-6, 1e-5, 1e-4, 1e-3):
        n = max(1, int(round(1.0 / (rate_hz * step))))
        if n <= 65536:
            return 1.0 / (n * step)
    return 1.0 / (65536 * 1e-3)


@dataclass
class StreamFaults:
    hold_s: float = 0.0  # hold packets back this long from when set (rig clock)
    stall: bool = False
    scan_overlap: bool = False
    garble: bool = False

    def clear(self) -> None:
        self.hold_s, self.stall, self.scan_overlap, self.garble = 0.0, False, False, False


class SimLabJackT:
    """The simulated T7 (see the module docstring)."""

    kind = "labjack"

    def __init__(self, name: str, rig, *, unit: int = 1, serial: int = 470_012_345, device_name: str = "velab-sim-T7",
                 shunt_ohm=249.0, calibration: T7Calibration = SIM_CALIBRATION,
                 on_digital: Callable[[int, bool, float], None] | None = None):
        self.name, self.rig, self.unit = name, rig, unit
        self.faults = DeviceFaults()
        self.stream_faults = StreamFaults()
        self.shunt_ohm = np.broadcast_to(np.asarray(shunt_ohm, dtype=float), (4,)).copy()
        self.calibration = calibration
        self.on_digital = on_digital
        self.image: dict[int, int] = {}
        self._lock = threading.RLock()
        self._put("PRODUCT_ID", 7.0)
        self._put("HARDWARE_VERSION", 1.3)
        self._put("FIRMWARE_VERSION", 1.0299)
        self._put("SERIAL_NUMBER", serial)
        name_bytes = device_name.encode("ascii")[:ljr.STRING_BYTES - 1].ljust(ljr.STRING_BYTES, b"\0")
        for i in range(25):
            self.image[ljr.reg("DEVICE_NAME_DEFAULT").address + i] = int.from_bytes(name_bytes[2 * i:2 * i + 2], "big")
        self.image.update({55100: 0x0011, 55101: 0x2233})  # TEST: always 0x00112233
        self._flash = np.array(calibration.to_floats(), dtype=">f4").view(">u4")
        self.fio_state = 0
        self.fio_direction = 0
        self._session: _Session | None = None
        self._ended: _Session | None = None  # a stream ended by its device with its last packet not yet all sent
        self.client: socket.socket | None = None  # the stream connection (set by the handle)
        self.packets_sent = 0

    # ------------------------------------------------------------ the register image
    def _put(self, name: str, value, n: int | None = None) -> None:
        r = ljr.reg(name)
        a = r.address if n is None else ljr.indexed(name, n)
        for i, w in enumerate(encode_value(value, r.dtype)):
            self.image[a + i] = w

    def _get(self, name: str, n: int | None = None):
        r = ljr.reg(name)
        a = r.address if n is None else ljr.indexed(name, n)
        return decode_registers([self.image.get(a + i, 0) for i in range(r.words)], r.dtype)

    def layout(self) -> list[tuple[int, int]]:
        return [(0, 2 * N_AIN), (2000, 8), (2500, 1), (2600, 1), (2800, 2), (2850, 2), (4002, 28), (4100, 256),
                (4990, 2), (40000, 2 * N_AIN), (41000, N_AIN), (41500, N_AIN), (55100, 2), (60000, 6), (60028, 2),
                (60500, 25), (61810, 4)]

    @property
    def streaming(self) -> bool:
        return self._session is not None

    def read(self, address: int, count: int) -> list[int]:
        with self._lock:
            now = self.rig.clock.now()
            end = address + count
            if address < 2 * N_AIN:
                if self.streaming:
                    raise _Refused(DEVICE_FAILURE)  # no command-response AIN while streaming
                mA = self.rig.analog_inputs(np.array([now]))[0]
                for ch in range(N_AIN):
                    v = float(mA[ch] * self.shunt_ohm[ch] / 1000.0) if ch < 4 else 0.0
                    self._put("AIN#(0:249)", float(np.clip(v, -10.6, 10.6)), ch)
            flash = ljr.reg("INTERNAL_FLASH_READ").address
            if address <= flash < end or address <= flash + 1 < end:
                if (end - address) % 2 or address != flash:
                    raise _Refused(ILLEGAL_VALUE)  # "read size must be an even number of registers"
                k = (int(self._get("INTERNAL_FLASH_READ_POINTER")) - ljr.T7_CAL_FLASH_ADDRESS) // 4
                for i in range(count // 2):
                    word = int(self._flash[k + i]) if 0 <= k + i < self._flash.size else 0xFFFFFFFF  # erased
                    self.image[flash + 2 * i], self.image[flash + 2 * i + 1] = word >> 16, word & 0xFFFF
            self.image[2500] = self.fio_state
            self.image[2600] = self.fio_direction
            self._put("DIO_STATE", self.fio_state)
            self._put("DIO_DIRECTION", self.fio_direction)
            self._put("STREAM_ENABLE", 1 if self.streaming else 0)
            return [self.image.get(a, 0) for a in range(address, end)]

    def write(self, address: int, values: list[int]) -> int | None:
        try:
            with self._lock:
                return self._write(address, list(values))
        except _Refused as exc:
            return exc.code

    def _write(self, address: int, values: list[int]) -> int | None:
        now = self.rig.clock.now()
        n = len(values)
        if 2000 <= address and address + n <= 2008:
            for i, v in enumerate(values):
                self._set_line(address - 2000 + i, bool(v & 1), now)
            return None
        if address == 2500 and n == 1:  # FIO_STATE: the upper byte inhibits lines
            for line in range(8):
                if not values[0] >> (8 + line) & 1 and self.fio_direction >> line & 1:
                    self._set_line(line, bool(values[0] >> line & 1), now)
            return None
        if address == 2600 and n == 1:
            keep = values[0] >> 8
            self.fio_direction = (self.fio_direction & keep) | (values[0] & 0xFF & ~keep)
            return None
        if 4002 <= address and address + n <= 4030:
            if self.streaming:
                raise _Refused(DEVICE_FAILURE)  # STREAM_IS_ACTIVE (2605)
            for i, v in enumerate(values):
                self.image[address + i] = v
            if address <= 4002 < address + n:  # the rate as the device will run it
                self._put("STREAM_SCANRATE_HZ", actual_scan_rate(max(1e-3, float(self._get("STREAM_SCANRATE_HZ")))))
            return None
        if 4100 <= address and address + n <= 4356:
            for i, v in enumerate(values):
                self.image[address + i] = v
            return None
        if address == 4990 and n == 2:
            enable = decode_registers(values, "uint32")
            if enable == 1:
                self._start(now)
            elif enable == 0:
                if not self.streaming:
                    raise _Refused(DEVICE_FAILURE)  # STREAM_NOT_RUNNING (2620)
                self._session = None
            else:
                raise _Refused(ILLEGAL_VALUE)
            return None
        if 40000 <= address and address + n <= 40000 + 2 * N_AIN and n % 2 == 0:
            for i in range(0, n, 2):
                if decode_registers(values[i:i + 2], "float32") not in (0.0, 10.0, 1.0, 0.1, 0.01):
                    raise _Refused(ILLEGAL_VALUE)
                self.image[address + i], self.image[address + i + 1] = values[i], values[i + 1]
            return None
        if (41000 <= address and address + n <= 41000 + N_AIN) or (41500 <= address and address + n <= 41500 + N_AIN):
            for i, v in enumerate(values):
                self.image[address + i] = v
            return None
        if address == 61810 and n == 2:
            self.image[61810], self.image[61811] = values
            return None
        raise _Refused(ILLEGAL_ADDRESS)

    def _set_line(self, line: int, level: bool, now: float) -> None:
        self.fio_direction |= 1 << line
        self.fio_state = (self.fio_state & ~(1 << line)) | (int(level) << line)
        if self.on_digital is not None:  # every write reaches it (the valve's wiring decides what an edge is)
            self.on_digital(line, level, now)

    # ------------------------------------------------------------ stream
    def _start(self, now: float) -> None:
        if self.streaming:
            raise _Refused(DEVICE_FAILURE)  # STREAM_IS_ACTIVE
        nch = int(self._get("STREAM_NUM_ADDRESSES"))
        spp = int(self._get("STREAM_SAMPLES_PER_PACKET"))
        rate = float(self._get("STREAM_SCANRATE_HZ"))
        target = int(self._get("STREAM_AUTO_TARGET"))
        size = int(self._get("STREAM_BUFFER_SIZE_BYTES")) or T7_BUFFER_DEFAULT
        datatype = decode_registers([self.image.get(4018, 0), self.image.get(4019, 0)], "uint32")
        if not (1 <= nch <= 128 and 1 <= spp <= MAX_SAMPLES_PER_PACKET and rate > 0
                and rate * nch <= T7_MAX_SAMPLE_RATE and target & ljr.AUTO_TARGET_ETHERNET and datatype == 0
                and size & (size - 1) == 0 and size <= 32768):
            raise _Refused(ILLEGAL_VALUE)
        scan = [int(self._get("STREAM_SCANLIST_ADDRESS#(0:127)", i)) for i in range(nch)]
        if any(a % 2 or not 0 <= a < 2 * N_AIN for a in scan):
            raise _Refused(ILLEGAL_VALUE)  # only AIN# is streamable here
        gains = []
        for a in scan:
            rng = float(self._get("AIN#(0:249)_RANGE", a // 2)) or 10.0
            gains.append({10.0: 0, 1.0: 1, 0.1: 2, 0.01: 3}[round(rng, 2)])
        self._ended = None
        # the FIFO holds the device's STREAM_BUFFER_SIZE_BYTES of *host* time: on a clock K x real time, K x as many
        # bytes (velab.simulators.clock.buffer_scale; without it the fast clock's 32 KB were 0.7 s of a loaded host's
        # hiccup, and a run lost 12437 scans to an auto-recovery the real device would never have needed)
        room = int(size * buffer_scale(self.rig.clock)) // 2
        self._session = _Session(t0=now, rate=rate, inputs=[a // 2 for a in scan], gains=gains, spp=spp,
                                 capacity=room - room % nch,
                                 autorecover_disabled=bool(self._get("STREAM_AUTORECOVER_DISABLE")))

    def tick(self) -> None:
        """Advance the stream to the rig clock's now: scan, fill the FIFO, send what is due (the handle's thread)."""
        with self._lock:
            s = self._session
            if s is None and self._ended is not None:  # the packet that ended the stream, still going out
                self._flush(self._ended)
                if not self._ended.outgoing:
                    self._ended = None
            if s is None or self.stream_faults.stall:
                return
            now = self.rig.clock.now()
            due = int(math.floor((now - s.t0) * s.rate + 1e-9))
            if due > s.generated:
                self._scan(s, due)
            if self._session is None:
                return
            if self.stream_faults.hold_s:
                s.hold_until = now + self.stream_faults.hold_s
                self.stream_faults.hold_s = 0.0
            if now < s.hold_until:
                return
            self._send_due(s)

    def _scan(self, s: "_Session", due: int) -> None:
        k = np.arange(s.generated, due)
        s.generated = due
        if s.recovering:
            s.skipped += k.size
            return
        t = s.t0 + k / s.rate
        mA = self.rig.analog_inputs(t)
        raw = np.empty((k.size, len(s.inputs)), np.uint16)
        for j, (inp, g) in enumerate(zip(s.inputs, s.gains)):
            volts = mA[:, inp] * self.shunt_ohm[inp] / 1000.0 if inp < 4 else np.zeros(k.size)
            raw[:, j] = self.calibration.binary(volts, g)
        flat = raw.ravel()
        room = s.capacity - s.fifo.size
        if flat.size > room:
            keep = max(0, room - room % len(s.inputs))
            s.fifo = np.concatenate([s.fifo, flat[:keep]])
            if s.autorecover_disabled:
                self._final_packet(s, ljr.STREAM_BUFFER_FULL)
                return
            s.recovering = True
            s.skipped = (flat.size - keep) // len(s.inputs)
        else:
            s.fifo = np.concatenate([s.fifo, flat])

    def _send_due(self, s: "_Session") -> None:
        # what is still to go first: a packet the host's socket took only part of, or one made before the host's
        # connection was accepted (with no retry here it was held for good: the stream fell silent)
        self._flush(s)
        if s.recovering and s.fifo.size < s.spp:  # emptied: new scans again, after a dummy scan
            status_end = s.skipped
            s.recovering, s.skipped = False, 0
            if status_end > 0xFFFF:
                self._final_packet(s, ljr.STREAM_AUTO_RECOVER_END_OVERFLOW)
                return
            s.end_at = s.fifo.size  # the dummy's position: the packet carrying it has status 2941
            s.end_skipped = status_end
            s.fifo = np.concatenate([s.fifo, np.full(len(s.inputs), DUMMY_SAMPLE, np.uint16)])
        while not s.outgoing and s.fifo.size >= s.spp:
            if self.stream_faults.scan_overlap:
                self.stream_faults.scan_overlap = False
                self._final_packet(s, ljr.STREAM_SCAN_OVERLAP)
                return
            data, s.fifo = s.fifo[:s.spp], s.fifo[s.spp:]
            status, info = (ljr.STREAM_AUTO_RECOVER_ACTIVE if s.recovering else 0), 0
            if s.end_at is not None and s.end_at < s.spp:
                status, info, s.end_at = ljr.STREAM_AUTO_RECOVER_END, s.end_skipped, None
            elif s.end_at is not None:
                s.end_at -= s.spp
            s.outgoing = self._packet(s, data, status, info)
            self._flush(s)

    def _packet(self, s: "_Session", data, status: int, info: int) -> bytes:
        pkt = encode_packet(s.tid, data, backlog_bytes=2 * s.fifo.size, status=status, additional=info,
                            unit=self.unit)
        s.tid = (s.tid + 1) & 0xFFFF
        if self.stream_faults.garble:
            self.stream_faults.garble = False
            pkt = bytes(b ^ 0x5A for b in pkt[:16]) + pkt[16:]
        return pkt

    def _final_packet(self, s: "_Session", status: int) -> None:
        """A packet reporting a status that ends the stream (STREAM_ENABLE reads 0 afterwards)."""
        s.outgoing += self._packet(s, np.zeros(0, np.uint16), status, 0)
        self._flush(s)
        self._session = None
        self._ended = s if s.outgoing else None

    def _flush(self, s: "_Session") -> None:
        c = self.client
        if c is None or not s.outgoing:
            return  # no host connected: the FIFO fills (and auto-recovers), as on the device
        try:
            sent = c.send(s.outgoing, socket.MSG_DONTWAIT)
            s.outgoing = s.outgoing[sent:]
            if not s.outgoing:
                self.packets_sent += 1
        except BlockingIOError:
            pass  # the host is slow: back-pressure into the FIFO
        except OSError:
            self.client = None

    def flush(self) -> None:
        with self._lock:
            for s in (self._ended, self._session):
                if s is not None:
                    self._flush(s)


class _Refused(Exception):
    def __init__(self, code: int):
        super().__init__(code)
        self.code = code


@dataclass
class _Session:
    t0: float
    rate: float
    inputs: list
    gains: list
    spp: int
    capacity: int  # samples the FIFO holds (whole scans)
    autorecover_disabled: bool
    generated: int = 0
    fifo: np.ndarray = None
    tid: int = 0
    recovering: bool = False
    skipped: int = 0
    end_at: int | None = None
    end_skipped: int = 0
    outgoing: bytes = b""
    hold_until: float = -math.inf

    def __post_init__(self):
        if self.fifo is None:
            self.fifo = np.zeros(0, np.uint16)

