"""LabJack T-series DAQ (T7; T4 by profile) over Ethernet: one driver, velab's Modbus layer injected.

    with LabJackT(open_bus(settings, connect=False), "labjack_t7") as lj:   # open() on enter
        lj.identify()                         # {"model": "T7", "serial": ..., "firmware": ...}
        lj.read_analog("pressure")            # command-response AIN read -> Reading (not while streaming)
        lj.write_digital(0, True)             # FIO0 high: fires the valve
        rate = lj.configure(2000.0, ["pressure", "valve_position"])
        lj.start()                            # 702 connection, STREAM_ENABLE = 1, reader thread
        block = lj.get_block(timeout=1.0)     # SampleBlock (raw binary, mA, Pa / %, per-sample quality)
        lj.latest("pressure")                 # newest streamed sample, or None when not streaming
        lj.stop()

Registers: velab.drivers.labjack_registers (LabJack's map); packets and calibration: velab.drivers.labjack_stream
(datasheet 3.2.4 "Low-Level Stream"). Stream setup order (3.2.4 "Setup"): the stream registers, the scan list,
STREAM_DATATYPE = 0, STREAM_ENABLE = 1 last; the 702 connection is opened before the enable.

Conditions, each named within seconds: a lost packet (transaction id gap) -> ``lost_before`` of the next block
(exact: whole packets); auto-recovery (2940 .. 2941) -> the skipped scans as ``lost_before``, ``overrun``;
STREAM_SCAN_OVERLAP, STREAM_AUTO_RECOVER_END_OVERFLOW, STREAM_BUFFER_FULL -> StreamFault (the stream is not
continuous, or has stopped); no packet for ``data_timeout_s`` (the profile's ``data_s``, at least
SILENT_PACKETS packet intervals) -> StreamSilent; the 702 connection closed ->
DeviceDisconnected. A fatal error ends the reader: ``get_block`` raises it, ``error`` keeps it.
"""

from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from velab.drivers import labjack_registers as ljr
from velab.drivers.base import (DeviceDisconnected, DeviceError, DeviceException, DeviceFault, DeviceTimeout,
                                ImplausibleReply, ProtocolError, Reading, StreamSilent)
from velab.drivers.blocks import SampleBlock, quality_limits, signal_quality, worst_quality
from velab.drivers.labjack_profile import LabJackProfile, LJChannel, load_profile
from velab.drivers.labjack_stream import (DUMMY_SAMPLE, MAX_SAMPLES_PER_PACKET, PacketReader, StreamPacket,
                                          T7Calibration)
from velab.drivers.modbus import RegisterBus, decode_registers, encode_value
from velab.drivers.modbus_transport import ByteTransport, TcpTransport
from velab.drivers.silence import Silence

READ_WAIT_S = 0.05  # one read of the 702 connection waits at most this
QUEUE_BLOCKS = 256
PACKETS_PER_S = 20  # samples_per_packet = 0: about this many packets a second
# The device sends a packet every samples_per_packet / channels scans: up to 512 scans, and below 20 scans/s
# (auto) one scan a packet, 1 s apart at 1 scan/s, where the profile's data_s (1 s) alone would name a sound
# stream silent. The silence that does is at least this many packet intervals (LJM's default receive timeout
# is likewise calculated from the scan rate: LabJackM.h, LJM_STREAM_RECEIVE_TIMEOUT_MODE_CALCULATED).
SILENT_PACKETS = 3
FATAL_STATUS = (ljr.STREAM_SCAN_OVERLAP, ljr.STREAM_AUTO_RECOVER_END_OVERFLOW, ljr.STREAM_BUFFER_FULL,
                ljr.STREAM_BURST_COMPLETE)


class StreamFault(DeviceFault):
    """The device reported a stream status that ends a continuous record: ``status`` (the code) and
    ``status_name`` (LabJack's name: STREAM_SCAN_OVERLAP, STREAM_BUFFER_FULL ...)."""

    def __init__(self, message: str, status: int, *, device: str | None = None):
        super().__init__(message, device=device)
        self.status = status
        self.status_name = ljr.STREAM_STATUS.get(status, f"status {status}")


@dataclass
class LJStreamStats:
    packets: int = 0
    samples: int = 0  # scans delivered
    lost: int = 0  # scans lost (packet gaps + auto-recovery skips)
    lost_packets: int = 0
    auto_recoveries: int = 0  # STREAM_AUTO_RECOVER_END seen
    max_backlog_bytes: int = 0
    blocks: int = 0


def auto_samples_per_packet(rate_hz: float, n_channels: int) -> int:
    """About PACKETS_PER_S packets a second, whole scans, at most 512 samples (LabJack's TCP maximum)."""
    scans = max(1, int(round(rate_hz / PACKETS_PER_S)))
    per = min(scans * n_channels, MAX_SAMPLES_PER_PACKET)
    return max(n_channels, per - per % n_channels)


class LabJackT:
    """A LabJack T7/T4: ``bus`` (velab's RegisterBus on port 502), ``profile`` (name, path or profile);
    ``stream_transport``: a factory of the 702 byte transport (default: TCP to the profile's host and
    ``stream_port``)."""

    kind = "labjack"

    def __init__(self, bus: RegisterBus, profile: LabJackProfile | str | None = None, *, name: str | None = None,
                 stream_transport: Callable[[], ByteTransport] | None = None, host: str | None = None,
                 stream_port: int | None = None, density_kg_m3: float = 998.2,
                 clock: Callable[[], float] = time.time):
        self.bus = bus
        self.profile = load_profile(profile or "labjack_t7")
        self.name = name or self.profile.name
        self.density_kg_m3 = density_kg_m3
        self.clock = clock
        host = host or self.profile.host
        port = stream_port or self.profile.stream_port
        self._stream_transport = stream_transport or (lambda: TcpTransport(host, port, self.profile.command_s * 4))
        self.calibration: T7Calibration | None = None
        self.error: DeviceError | None = None
        self.stats = LJStreamStats()
        self._channels: tuple[LJChannel, ...] = ()
        self._rate = 0.0
        self._spp = 0
        self._thread: threading.Thread | None = None
        self._stop_evt = threading.Event()
        self._queue: queue.Queue = queue.Queue(QUEUE_BLOCKS)
        self._latest: dict[str, Reading] = {}
        self._lock = threading.Lock()
        self._link: ByteTransport | None = None
        # STREAM_ENABLE = 1 written by start() and not yet 0 by stop(): the device streams as far as the host knows,
        # even once the reader has ended on a fatal error (``error``); its AIN# are then not readable by
        # command-response (the device refuses: datasheet 3.2)
        self._enabled = False

    # ------------------------------------------------------------ bus access (errors name this device)
    def _named(self, exc: DeviceError) -> DeviceError:
        exc.device = self.name
        return exc

    def _read(self, name: str, n: int | None = None):
        r = ljr.reg(name) if n is None else None
        address = ljr.indexed(name, n) if n is not None else r.address
        r = r or ljr.reg(name)
        try:
            regs = self.bus.read_holding(address, r.words)
        except DeviceError as exc:
            raise self._named(exc)
        if r.type == "STRING":
            raw = b"".join(w.to_bytes(2, "big") for w in regs)
            return raw.split(b"\0", 1)[0].decode("ascii", "replace")
        return decode_registers(regs, r.dtype)

    def _write(self, name: str, value, n: int | None = None) -> None:
        r = ljr.reg(name)
        address = r.address if n is None else ljr.indexed(name, n)
        try:
            self.bus.write_registers(address, encode_value(value, r.dtype))
        except DeviceError as exc:
            raise self._named(exc)

    # ------------------------------------------------------------ connection and identity
    def open(self) -> "LabJackT":
        """Connect, check the device is the profile's model, read its calibration constants."""
        connect = getattr(self.bus, "connect", None)
        if connect is not None:
            try:
                connect()
            except DeviceError as exc:
                raise self._named(exc)
        pid = self._read("PRODUCT_ID")
        if int(round(pid)) != self.profile.product_id:
            raise ImplausibleReply(f"{self.name}: PRODUCT_ID {pid:g}, but the profile {self.profile.path} is for a "
                                   f"{self.profile.model}", device=self.name)
        self.calibration = self._read_calibration()
        return self

    def _read_calibration(self) -> T7Calibration:
        if self.profile.calibration == "nominal":
            return T7Calibration.nominal()
        # 20.0.1: float32 constants from 0x3C4000 via INTERNAL_FLASH_READ_POINTER / INTERNAL_FLASH_READ; the first
        # 16 are the high-speed converter's (the stream's). The pointer is written before each two-register read:
        # the map does not say whether it advances after a read.
        floats = []
        for i in range(16):
            self._write("INTERNAL_FLASH_READ_POINTER", ljr.T7_CAL_FLASH_ADDRESS + 4 * i)
            floats.append(self._flash_float())
        try:
            return T7Calibration.from_floats(floats)
        except ProtocolError as exc:
            raise self._named(exc.again(f"{self.name}: {exc}"))

    def _flash_float(self) -> float:
        try:
            regs = self.bus.read_holding(ljr.reg("INTERNAL_FLASH_READ").address, 2)
        except DeviceError as exc:
            raise self._named(exc)
        return float(decode_registers(regs, "float32"))

    def identify(self) -> dict:
        """What the device says about itself (PRODUCT_ID, SERIAL_NUMBER, FIRMWARE_VERSION, DEVICE_NAME_DEFAULT)."""
        pid = self._read("PRODUCT_ID")
        return {"manufacturer": "LabJack", "model": f"T{int(round(pid))}", "product_id": pid,
                "serial": int(self._read("SERIAL_NUMBER")), "firmware": round(float(self._read("FIRMWARE_VERSION")), 4),
                "hardware": round(float(self._read("HARDWARE_VERSION")), 4), "name": self._read("DEVICE_NAME_DEFAULT"),
                "calibration": self.calibration.source if self.calibration else None}

    def close(self) -> None:
        if self._thread is not None:
            try:
                self.stop()
            except DeviceError:
                pass
        self.bus.close()

    def __enter__(self) -> "LabJackT":
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------ command-response
    def channel(self, key) -> LJChannel:
        return self.profile.channel(key)

    def read_analog(self, channel) -> Reading:
        """One command-response read of a channel's AIN (volts) -> engineering units, NE43 quality. The
        device cannot read analogue inputs by command-response while it streams (datasheet 3.2): refused."""
        c = self.channel(channel)
        if self._enabled:
            err = self.error
            if err is not None and not self.streaming:  # the stream's own outcome, not a read the device refuses
                raise self._named(err.again(f"{self.name}: {c.name}: no reading: the stream (still enabled) ended: "
                                            f"{err}"))
            raise DeviceException(f"{self.name}: {c.name}: AIN{c.ain} cannot be read by command-response while "
                                  f"streaming (use latest())", device=self.name)
        volts = float(self._read("AIN#(0:249)", c.ain))
        sig = float(c.signal(volts))
        return Reading(c.calibration.value(sig), c.calibration.units, self.clock(), c.calibration.quality(sig),
                       raw=volts)

    def write_digital(self, line: int, level: bool) -> None:
        """FIO#: the line becomes an output at ``level`` (the map: a write "also configures the direction")."""
        if not 0 <= int(line) <= 7:
            raise ValueError(f"{self.name}: FIO line {line} outside 0..7")
        self._write("FIO#(0:7)", 1 if level else 0, int(line))

    def read_digital(self) -> tuple[bool, ...]:
        """FIO0..FIO7 levels from FIO_STATE (outputs read back the terminal's level)."""
        word = int(self._read("FIO_STATE"))
        return tuple(bool(word >> i & 1) for i in range(8))

    def fire_valve(self, level: bool = True) -> None:
        """The profile's valve-trigger line to its active (``level``) state."""
        line = self.profile.valve_trigger
        if line is None:
            raise DeviceException(f"{self.name}: the profile {self.profile.path} has no [digital] valve_trigger")
        self.write_digital(line, level == self.profile.active_high)

    # ------------------------------------------------------------ stream
    @property
    def streaming(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    @property
    def rate_hz(self) -> float:
        return self._rate

    @property
    def data_timeout_s(self) -> float:
        """No stream packet for this long (the time the reader listened): StreamSilent. The profile's
        ``data_s``, and at least SILENT_PACKETS intervals between the configured stream's packets."""
        if not (self._rate > 0 and self._channels):
            return self.profile.data_s
        return max(self.profile.data_s, SILENT_PACKETS * (self._spp / len(self._channels)) / self._rate)

    def configure(self, rate_hz: float | None = None, channels=None) -> float:
        """Stop any stream, set the inputs (range, single ended) and the stream registers; the scan rate the
        device reports back (it rounds the scan interval)."""
        if self.streaming:
            raise DeviceException(f"{self.name}: configure() while streaming (stop first)", device=self.name)
        prof = self.profile
        rate = float(rate_hz if rate_hz is not None else prof.rate_hz)
        chans = tuple(self.channel(k) for k in (channels if channels is not None else [c.name for c in prof.channels]))
        if not chans or len({c.ain for c in chans}) != len(chans):
            raise ValueError(f"{self.name}: acquire one or more distinct channels, got {[c.name for c in chans]}")
        if not 0 < rate * len(chans) <= prof.max_sample_rate_hz:
            raise ValueError(f"{self.name}: {rate:g} scans/s x {len(chans)} channels is beyond the "
                             f"{prof.max_sample_rate_hz:g} samples/s of a {prof.model}")
        if self.calibration is None:
            self.calibration = self._read_calibration()
        for c in chans:
            self.calibration._gain(c.gain_index)  # ValueError now, not in the reader
        self._stop_stream_register()
        for c in chans:
            self._write("AIN#(0:249)_RANGE", c.range, c.ain)
            self._write("AIN#(0:249)_NEGATIVE_CH", ljr.SINGLE_ENDED, c.ain)
        spp = prof.samples_per_packet or auto_samples_per_packet(rate, len(chans))
        for name, value in (("STREAM_SCANRATE_HZ", rate), ("STREAM_NUM_ADDRESSES", len(chans)),
                            ("STREAM_SAMPLES_PER_PACKET", spp), ("STREAM_SETTLING_US", prof.settling_us),
                            ("STREAM_RESOLUTION_INDEX", prof.resolution_index),
                            ("STREAM_BUFFER_SIZE_BYTES", prof.buffer_size_bytes),
                            ("STREAM_AUTO_TARGET", ljr.AUTO_TARGET_ETHERNET), ("STREAM_NUM_SCANS", 0)):
            self._write(name, value)
        words = [w for c in chans for w in encode_value(ljr.ain(c.ain), "uint32")]
        try:
            self.bus.write_registers(ljr.scanlist_address(0), words)
        except DeviceError as exc:
            raise self._named(exc)
        self._write("STREAM_DATATYPE", 0)
        actual = float(self._read("STREAM_SCANRATE_HZ"))
        if not actual > 0:
            raise ImplausibleReply(f"{self.name}: STREAM_SCANRATE_HZ reads {actual:g}", device=self.name)
        self._channels, self._rate, self._spp = chans, actual, spp
        return actual

    def _stop_stream_register(self) -> None:
        try:
            self._write("STREAM_ENABLE", 0)
        except DeviceException:
            pass  # STREAM_NOT_RUNNING (2620): "stream was already disabled"

    def start(self) -> None:
        """Open the 702 connection, STREAM_ENABLE = 1 (last), start the reader thread."""
        if self._thread is not None:
            raise DeviceException(f"{self.name}: already streaming", device=self.name)
        if not self._channels:
            self.configure()
        link = self._stream_transport()
        try:
            link.open()
        except DeviceDisconnected as exc:
            raise self._named(exc.again(f"{self.name}: stream port: {exc}"))
        self._link = link
        self.error = None
        self.stats = LJStreamStats()
        self._queue = queue.Queue(QUEUE_BLOCKS)
        with self._lock:
            self._latest = {}
        try:
            self._write("STREAM_ENABLE", 1)
        except DeviceError:
            link.close()
            self._link = None
            raise
        self._enabled = True
        self._stop_evt.clear()
        self._thread = threading.Thread(target=self._run, name=f"{self.name} stream reader", daemon=True)
        self._thread.start()

    def stop(self) -> LJStreamStats:
        """STREAM_ENABLE = 0, end the reader, close the 702 connection. A fatal error already delivered is not
        raised again (it stays in ``error``)."""
        t = self._thread
        if t is None:
            return self.stats
        self._stop_evt.set()
        t.join(READ_WAIT_S * 4 + self.data_timeout_s + 2.0)
        self._thread = None
        with self._lock:
            self._latest = {}
        if self._link is not None:
            self._link.close()
            self._link = None
        try:
            self._queue.put_nowait(None)
        except queue.Full:
            pass
        if not isinstance(self.error, DeviceDisconnected):
            self._stop_stream_register()
        self._enabled = False
        return self.stats

    def get_block(self, timeout: float | None = None) -> SampleBlock:
        """The next block; the reader's fatal error; DeviceTimeout if nothing came within ``timeout``."""
        timeout = self.data_timeout_s if timeout is None else timeout
        try:
            item = self._queue.get(timeout=timeout)
        except queue.Empty:
            if self.error is not None:
                raise self.error from None
            raise DeviceTimeout(f"{self.name}: no stream block within {timeout:g} s", device=self.name) from None
        if isinstance(item, BaseException):
            raise item
        if item is None:
            raise DeviceException(f"{self.name}: stream is stopped", device=self.name)
        return item

    def get_blocks(self) -> list[SampleBlock]:
        """Every block queued, without waiting (a pending error after the data, at the next call)."""
        out = []
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                return out
            if isinstance(item, BaseException):
                if out:
                    self._queue.put(item)
                    return out
                raise item
            if item is not None:
                out.append(item)

    def latest(self, channel) -> Reading | None:
        """The newest streamed sample of a channel (an immutable Reading), None when not streaming."""
        name = self.channel(channel).name
        with self._lock:
            return self._latest.get(name) if self.streaming else None

    def pressure_source(self, name: str, clock_scale: float = 1.0):
        """velab's PressureSource over this driver (velab.drivers.pressure_source.pressure_source asks for it)."""
        from velab.drivers.labjack_source import LabJackSource

        return LabJackSource(self, name, clock_scale)

    # ------------------------------------------------------------ the reader thread
    def _run(self) -> None:
        reader = PacketReader(f"{self.name} stream")
        silence = Silence.for_wait(READ_WAIT_S)
        state = _Decode(len(self._channels), self._spp)
        silent_s = self.data_timeout_s
        try:
            while not self._stop_evt.is_set():
                data = self._link.read(65536, time.monotonic() + READ_WAIT_S)
                packets = reader.feed(data) if data else []
                if packets:
                    self._deliver(state, packets, time.time())
                    silence.reset()
                elif silence.passed() > silent_s:
                    raise StreamSilent(f"{self.name}: no stream packet on port {self.profile.stream_port} for "
                                       f"{silent_s:g} s ({self.stats.packets} packets so far)", device=self.name)
        except DeviceError as exc:
            self._fail(exc)
        except Exception as exc:  # a bug: still a named outcome
            err = DeviceError(f"{self.name}: stream reader failed: {type(exc).__name__}: {exc}", device=self.name)
            err.__cause__ = exc
            self._fail(err)

    def _fail(self, exc: DeviceError) -> None:
        if isinstance(exc, DeviceDisconnected):
            exc = exc.again(f"{self.name}: stream connection lost: {exc}")
        self._named(exc)
        self.error = exc
        while True:
            try:
                self._queue.put_nowait(exc)
                return
            except queue.Full:  # the error matters more than the oldest block
                try:
                    self._queue.get_nowait()
                except queue.Empty:
                    pass

    def _deliver(self, state: "_Decode", packets: list[StreamPacket], host_t: float) -> None:
        for raw, first, lost, overrun in state.blocks(packets, self):
            if raw.shape[0]:
                self._emit(self._block(raw, first, lost, overrun, host_t))

    def _block(self, raw: np.ndarray, first: int, lost: int, overrun: bool, host_t: float) -> SampleBlock:
        chans, cal = self._channels, self.calibration
        volts = np.column_stack([cal.volts(raw[:, j], c.gain_index) for j, c in enumerate(chans)])
        signal = np.column_stack([c.signal(volts[:, j]) for j, c in enumerate(chans)])
        values = np.column_stack([c.calibration.value(signal[:, j]) for j, c in enumerate(chans)])
        q = signal_quality(signal, quality_limits([c.calibration for c in chans]),
                           clipped_hi=raw == 0xFFFF, clipped_lo=raw == 0)
        b = SampleBlock(segment=0, first_index=first, rate_hz=self._rate, host_time_s=host_t, raw=raw,
                        signal=signal, values=values, channels=tuple(c.name for c in chans),
                        units=tuple(c.calibration.units for c in chans),
                        quality=tuple(worst_quality(q[:, j]) for j in range(len(chans))), lost_before=lost,
                        overrun=overrun, density_kg_m3=self.density_kg_m3, sample_quality=q)
        last = {c.name: Reading(float(values[-1, j]), c.calibration.units, host_t, worst_quality(q[-1:, j]),
                                device_time_s=(b.next_index - 1) / self._rate, raw=int(raw[-1, j]))
                for j, c in enumerate(chans)}
        with self._lock:
            self._latest = last
        return b

    def _emit(self, block: SampleBlock) -> None:
        # back-pressure: a slow consumer holds the reader, the device's buffer fills and auto-recovery counts
        # the loss exactly (never a silent drop here)
        while not self._stop_evt.is_set():
            try:
                self._queue.put(block, timeout=READ_WAIT_S)
                self.stats.blocks += 1
                self.stats.samples += block.n
                return
            except queue.Full:
                continue


class _Decode:
    """Packets -> contiguous runs of whole scans: transaction-id gaps and auto-recovery skips become
    ``lost_before``; fatal statuses raise StreamFault."""

    def __init__(self, n_channels: int, samples_per_packet: int):
        self.nch, self.spp = n_channels, samples_per_packet
        self.expected_tid = 0  # 3.2.4: the first packet after STREAM_ENABLE = 1 has transaction id 0
        self.next_scan = 0
        self.carry = np.zeros(0, np.uint16)  # samples of an incomplete scan (a packet boundary inside a scan)
        self.overrun = False  # auto-recovery in progress (2940 seen, 2941 not yet)

    def blocks(self, packets: list[StreamPacket], dev: LabJackT) -> list[tuple[np.ndarray, int, int, bool]]:
        """(raw scans (n, ch), first scan index, scans lost just before, overrun) per contiguous run."""
        self.runs, self.cur, self.first, self.lost_here, self.over_here = [], [], self.next_scan, 0, False
        for p in packets:
            dev.stats.packets += 1
            dev.stats.max_backlog_bytes = max(dev.stats.max_backlog_bytes, p.backlog_bytes)
            gap = (p.tid - self.expected_tid) & 0xFFFF
            self.expected_tid = (p.tid + 1) & 0xFFFF
            if gap:  # packets lost on the way: whole packets of samples (the partial scan goes with them)
                dev.stats.lost_packets += gap
                lost_samples = gap * self.spp + self.carry.size
                self.carry = np.zeros(0, np.uint16)
                self._gap(-(-lost_samples // self.nch), dev)
            if p.status in FATAL_STATUS:
                why = ": the stream stopped (buffer overflow)" if p.status == ljr.STREAM_BUFFER_FULL else ""
                raise StreamFault(f"{dev.name}: the device reports {ljr.STREAM_STATUS[p.status]} ({p.status}){why}, "
                                  f"backlog {p.backlog_bytes} bytes", p.status, device=dev.name)
            if p.status == ljr.STREAM_AUTO_RECOVER_END:
                # the data before the dummy scan, the skipped scans (additional status), the data after it
                before, after = self._split_at_dummy(np.concatenate([self.carry, p.samples]), dev)
                self.carry = np.zeros(0, np.uint16)
                self._add(before)
                dev.stats.auto_recoveries += 1
                self.overrun = True
                self._gap(p.additional, dev)  # the run after the gap is marked overrun
                self.overrun = False
                self._add(after)
                continue
            if p.status == ljr.STREAM_AUTO_RECOVER_ACTIVE:
                self.overrun = True  # the buffer is full: these data are valid, new scans are being discarded
            elif p.status != 0:
                raise ImplausibleReply(f"{dev.name}: unknown stream status {p.status}", device=dev.name)
            self._add(p.samples)
        if self.cur:
            self.runs.append((np.concatenate(self.cur), self.first, self.lost_here, self.over_here))
        return self.runs

    def _add(self, samples: np.ndarray) -> None:
        allv = np.concatenate([self.carry, samples])
        whole = allv.size - allv.size % self.nch
        self.carry = allv[whole:]
        scans = allv[:whole].reshape(-1, self.nch)
        if scans.shape[0]:
            self.cur.append(scans)
            self.next_scan += scans.shape[0]
            self.over_here = self.over_here or self.overrun

    def _gap(self, lost: int, dev: LabJackT) -> None:
        if not lost:
            return
        if self.cur:
            self.runs.append((np.concatenate(self.cur), self.first, self.lost_here, self.over_here))
            self.cur, self.lost_here, self.over_here = [], 0, False
        self.lost_here += lost
        self.over_here = self.over_here or self.overrun
        self.next_scan += lost
        self.first = self.next_scan
        dev.stats.lost += lost

    def _split_at_dummy(self, samples: np.ndarray, dev: LabJackT) -> tuple[np.ndarray, np.ndarray]:
        """The samples before and after the scan of 0xFFFF samples (STREAM_AUTO_RECOVER_END's separator)."""
        n = samples.size - samples.size % self.nch
        scans = samples[:n].reshape(-1, self.nch)
        dummy = np.flatnonzero((scans == DUMMY_SAMPLE).all(axis=1))
        if dummy.size == 0:
            raise ImplausibleReply(f"{dev.name}: STREAM_AUTO_RECOVER_END without its dummy scan", device=dev.name)
        k = int(dummy[0])
        return scans[:k].ravel(), np.concatenate([scans[k + 1:].ravel(), samples[n:]])


__all__ = ["LJStreamStats", "LabJackT", "SILENT_PACKETS", "StreamFault", "auto_samples_per_packet"]
