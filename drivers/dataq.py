"""DATAQ Instruments DI-series DAQ (DI-1100, DI-1110, DI-2108; USB CDC serial): one driver class.

Protocol: velab.drivers.dataq_protocol (from the vendor's "Data Acquisition Instrument Command Protocol",
2019; page numbers below refer to it); profile: velab.drivers.dataq_profile; docs/devices-dataq.md.

    daq = DataqDAQ(profile.url, profile)           # or a pyserial-like object (transport injected)
    daq.open(); daq.identify()                     # {"manufacturer": "DATAQ", "model": "DI-2108", ...}
    rate = daq.configure(2000, ["pressure", "valve_position"])   # the exact rate it will run at
    daq.start()                                    # reader thread -> bounded queue of SampleBlocks
    block = daq.get_block(timeout=1.0)             # or a named DeviceError
    daq.write_digital(0, True)                     # fire the valve (sent without echo while scanning, p.16)
    daq.latest("pressure")                         # newest sample (Reading) while streaming
    daq.stop(); daq.close()

The USB stream has no sample counter, header or checksum (p.60): what the driver can still tell is named.
No in-frame scan for ``data_s`` -> StreamSilent; the device's ``stop 01`` (its 1024-sample buffer overflowed,
it stopped scanning, p.50) -> DeviceFault; framing lost (a byte dropped or junk inserted, seen by the layout's
spare and complement bits) -> scans skipped until in frame again, their estimated count in ``lost_before``;
a disconnect -> reconnection (new segment, ``restarted``, gap estimated from host time) or, after
``reconnect_s``, DeviceDisconnected.
"""

from __future__ import annotations

import functools
import queue
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path
from types import MappingProxyType
from typing import Any, Callable

import numpy as np

from velab.drivers import dataq_protocol as dq
from velab.drivers.base import (
    DeviceDisconnected,
    DeviceError,
    DeviceException,
    DeviceFault,
    DeviceTimeout,
    ProfileError,
    ProtocolError,
    Reading,
    ReplyMismatch,
    StreamSilent,
)
from velab.drivers.blocks import QUALITY_CODES, SampleBlock, StuckDetector, quality_limits, signal_quality, worst_quality
from velab.drivers.dataq_profile import DataqChannel, DataqProfile, default_profile
from velab.drivers.silence import Silence

COMMAND_GAP_S = 0.01  # between commands sent while scanning (no echo to wait for; the buffer is small, p.16)


def find_ports() -> list[tuple[str, str]]:
    """(port, model) of every DATAQ instrument plugged in (USB VID 0x0683, p.8); model "" if the PID is
    not one of velab's models (or the device is in libusb mode)."""
    from serial.tools import list_ports

    out = []
    for p in list_ports.comports():
        if p.vid == dq.VENDOR_ID:
            m = dq.MODEL_BY_PID.get(p.pid)
            out.append((p.device, m.name if m else ""))
    return out


def _names_device(fn):
    @functools.wraps(fn)
    def wrapper(self, *args, **kw):
        try:
            return fn(self, *args, **kw)
        except DeviceError as exc:
            if exc.device is None:
                exc.device = self.name
            raise

    return wrapper


@dataclass
class DataqStats:
    scans: int = 0  # delivered
    blocks: int = 0
    bytes_read: int = 0
    resyncs: int = 0  # framing lost and found again
    skipped_bytes: int = 0
    lost_estimated: int = 0  # scans: framing losses and reconnection gaps (no counter: estimates)
    queue_dropped: int = 0
    reconnects: int = 0


@dataclass(frozen=True)
class DataqConfig:
    rate_hz: float  # exact: dividend / (srate x dec) (p.48)
    plan: dq.RatePlan
    layout: dq.ScanLayout
    channels: tuple[DataqChannel, ...]  # in scan-list order
    packet_code: int


class DataqDAQ:
    """Host driver for a DATAQ DI-1100 / DI-1110 / DI-2108. See the module docstring."""

    def __init__(self, transport: Any = None, profile: DataqProfile | None = None, *, name: str = "DATAQ DAQ"):
        self.profile = profile or default_profile()
        self.spec = self.profile.spec
        transport = transport if transport is not None else self.profile.url
        if transport is None:
            raise ValueError("DataqDAQ needs a port path / pyserial URL, a serial-like object, or a profile with url")
        self._url = transport if isinstance(transport, (str, Path)) else None
        self._port = None if self._url is not None else transport
        self.name = name
        self._rx = bytearray()
        self._wlock = threading.Lock()
        self._last_cmd = 0.0
        self._scanning = False
        self.config: DataqConfig | None = None
        self._wanted: tuple | None = None  # (rate, channels) to configure again (after read_analog)
        self._identity: dict | None = None
        self._dout = 0
        self._endo: int | None = None  # the endo mask sent on this connection
        self._thread: threading.Thread | None = None
        self._stop_evt = threading.Event()
        self._queue: queue.Queue | None = None
        self._callback = None
        self._on_error = None
        self.error: DeviceError | None = None
        self._stop_error: DeviceError | None = None
        self._latest: MappingProxyType = MappingProxyType({})
        self._din_latest: int | None = None
        self._stats = DataqStats()
        self._slock = threading.Lock()

    # ---------------------------------------------------------------- transport

    @_names_device
    def open(self) -> None:
        if self._port is not None and getattr(self._port, "is_open", True):
            return
        if self._url is None:
            try:
                self._port.open()
            except Exception as exc:
                raise DeviceDisconnected(f"{self.name}: cannot reopen port: {exc}") from exc
            return
        import serial

        try:
            self._port = serial.serial_for_url(str(self._url), baudrate=self.profile.baudrate,
                                               timeout=self.profile.poll_s, write_timeout=self.profile.command_timeout_s)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceDisconnected(f"{self.name}: cannot open {self._url}: {exc}") from exc

    def close(self) -> None:
        if self._thread is not None:
            try:
                self.stop()
            except DeviceError:
                pass
        self._close_port()

    def _close_port(self) -> None:
        if self._port is not None:
            try:
                self._port.close()
            except Exception:
                pass
        if self._url is not None:
            self._port = None
        self._rx.clear()
        self._endo = None  # a re-plugged device comes back with its ports re-initialised

    def __enter__(self) -> "DataqDAQ":
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _write(self, data: bytes) -> None:
        if self._port is None:
            raise DeviceDisconnected(f"{self.name}: port is not open")
        try:
            with self._wlock:
                self._port.write(data)
        except Exception as exc:
            if type(exc).__name__ == "SerialTimeoutException":
                raise DeviceTimeout(f"{self.name}: write of {data!r} timed out") from exc
            raise DeviceDisconnected(f"{self.name}: write failed: {exc}") from exc

    def _read(self, size: int) -> bytes:
        if self._port is None:
            raise DeviceDisconnected(f"{self.name}: port is not open")
        try:
            n = self._port.in_waiting
            return self._port.read(max(n, size))
        except Exception as exc:
            raise DeviceDisconnected(f"{self.name}: read failed: {exc}") from exc

    # ---------------------------------------------------------------- commands

    @_names_device
    def command(self, line: bytes) -> str:
        """Send one command (bytes ending in CR, dataq_protocol builds them) and return its response text.

        Not scanning: the echo must come back within command_s (p.16); a reply that is not the echo is a
        ReplyMismatch, "... not found" a DeviceException. Scanning: nothing echoes (p.16), so only commands
        that need no answer may be sent (dout); they are spaced by COMMAND_GAP_S."""
        if self._scanning:
            if not line.startswith(b"dout "):
                raise DeviceException(f"{self.name}: {line!r} refused while scanning (it would not echo, p.16)")
            wait = self._last_cmd + COMMAND_GAP_S - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            self._write(line)
            self._last_cmd = time.monotonic()
            return ""
        if self._port is None:
            self.open()
        self._write(line)
        reply = self._read_line(line)
        try:
            text = dq.reply_text(line, reply)
        except dq.ReplyError as exc:
            raise ReplyMismatch(f"{self.name}: {exc}") from None
        if text.endswith("not found"):
            raise DeviceException(f"{self.name}: {line.rstrip().decode()!r} -> {text!r}")
        return text

    def _read_line(self, sent: bytes) -> bytes:
        deadline = time.monotonic() + self.profile.command_timeout_s
        while True:
            while self._rx[:1] in (b"\n", b"\x00"):  # stray LF / NUL between replies (vendor examples strip them)
                del self._rx[:1]
            cr = self._rx.find(dq.CR)
            if cr >= 0:
                line = bytes(self._rx[:cr + 1])
                del self._rx[:cr + 1]
                return line
            if len(self._rx) > 256:
                raise ProtocolError(f"{self.name}: {sent.rstrip()!r} -> no CR in {bytes(self._rx[:32])!r}...")
            if time.monotonic() > deadline:
                more = self._read(0)
                if more:
                    self._rx += more
                    continue
                got = f" (got {bytes(self._rx)!r})" if self._rx else ""
                raise DeviceTimeout(f"{self.name}: no echo of {sent.rstrip().decode()!r} within "
                                    f"{self.profile.command_timeout_s:g} s{got}")
            self._rx += self._read(1)

    def _stop_idle(self) -> None:
        """``stop`` and skip whatever streamed before its echo (the device may have been left scanning).
        The echo must end the bytes and nothing follow it; the wait restarts while bytes come, 5 x command_s
        in all."""
        self._rx.clear()
        self._write(dq.stop())
        t_cmd = self.profile.command_timeout_s
        hard = time.monotonic() + 5 * t_cmd
        deadline = time.monotonic() + t_cmd
        buf = bytearray()
        while True:
            got = self._read(64)
            if got:
                buf += got
                deadline = time.monotonic() + t_cmd
                del buf[:-64]
                continue
            if buf.rstrip(b"\n\x00").endswith(dq.STOP_ECHO):
                return
            if time.monotonic() > min(deadline, hard):
                seen = f" (last bytes {bytes(buf[-16:])!r})" if buf else ""
                raise DeviceTimeout(f"{self.name}: no echo of 'stop' within {t_cmd:g} s{seen}")

    @_names_device
    def identify(self) -> dict:
        """What the device says through ``info`` (p.20): manufacturer (info 0), model (info 1), firmware
        (info 2, hex coded: 65 -> 1.01), serial number (info 6)."""
        if self._scanning:
            return dict(self._identity or {})
        self.open()
        self._stop_idle()
        maker = self.command(dq.info(0))
        number = self.command(dq.info(1))
        fw = self.command(dq.info(2))
        serial_no = self.command(dq.info(6))
        m = dq.MODEL_BY_NUMBER.get(number)
        self._identity = {"manufacturer": maker, "model": m.name if m else f"DI-{number}", "serial": serial_no,
                          "firmware": dq.firmware_text(fw)}
        return dict(self._identity)

    def _check_model(self) -> None:
        ident = self._identity or self.identify()
        if ident["manufacturer"] != "DATAQ":
            raise ReplyMismatch(f"{self.name}: 'info 0' -> {ident['manufacturer']!r}, not 'DATAQ': not a DATAQ instrument")
        if ident["model"] != self.spec.name:
            where = f" ({self.profile.path})" if self.profile.path else ""
            raise ProfileError(f"{self.name}: the profile{where} is for a {self.spec.name}, the device says it is a "
                               f"{ident['model']}", device=self.name)

    # ---------------------------------------------------------------- configuration

    def rate_range(self, n_channels: int | None = None) -> tuple[float, float]:
        return self.spec.rate_bounds(n_channels or max(1, len(self.profile.enabled)))

    @_names_device
    def configure(self, rate_hz: float | None = None, channels=None) -> float:
        """Stop, then binary mode, packet size, scan list, rate, digital outputs (pp.20, 38-52, 57).

        ``channels``: names or input numbers (default: the profile's). Returns the exact per-channel rate the
        device will run at (dividend / (srate x dec), p.48)."""
        if self._thread is not None:
            raise DeviceException(f"{self.name}: configure() while streaming (stop first)")
        return self._setup(rate_hz, channels)

    def _setup(self, rate_hz: float | None, channels) -> float:
        prof = self.profile
        keys = list(channels) if channels is not None else list(prof.enabled)
        chans = tuple(sorted({prof.channel(k).input: prof.channel(k) for k in keys}.values(), key=lambda c: c.input))
        rate = float(rate_hz if rate_hz is not None else prof.rate_hz)
        layout = dq.scan_layout(self.spec, [c.input for c in chans])
        plan = dq.rate_plan(self.spec, rate, len(chans))
        code = prof.packet_size if prof.packet_size >= 0 else dq.packet_code(plan.rate_hz * layout.scan_bytes)
        self.open()
        if self._identity is None:
            self.identify()  # (stops the device first)
        else:
            self._stop_idle()
        self._check_model()
        self.command(dq.encode(dq.ENCODE_BINARY))
        self.command(dq.ps(code))
        for pos, word in enumerate(layout.slist_words()):
            self.command(dq.slist(pos, word))
        self.command(dq.srate(plan.srate))
        if self.spec.dec_max > 1:
            self.command(dq.dec(plan.dec))
        if self.spec.deca:
            self.command(dq.deca(plan.deca))
        mask = sum(1 << d for d in prof.digital_outputs)
        if self.spec.digital_io and mask and self._endo != mask:
            # endo re-initialises every port (p.57): sent once per connection, so reconfiguring never pulses
            # an output that is on (the valve trigger)
            self.command(dq.endo(mask))
            self._endo = mask
            self.command(dq.dout(self._dout))
        self.config = DataqConfig(plan.rate_hz, plan, layout, chans, code)
        self._wanted = (rate, [c.name for c in chans])
        return plan.rate_hz

    # ---------------------------------------------------------------- digital I/O

    @_names_device
    def write_digital(self, line: int, level: bool) -> None:
        """Set output line Dn (a switch: on = True). Needs the line in the profile's [digital] outputs.
        While scanning ``dout`` is sent without waiting for an echo: none comes (p.16)."""
        if not self.spec.digital_io:
            raise DeviceException(f"{self.name}: the {self.spec.name} has no digital outputs (protocol p.57)")
        if line not in self.profile.digital_outputs:
            raise DeviceException(f"{self.name}: D{line} is not a digital output (profile [digital] outputs = "
                                  f"{list(self.profile.digital_outputs)})")
        new = (self._dout | (1 << line)) if level else (self._dout & ~(1 << line))
        if not self._scanning and self.config is None:
            self.configure(*(self._wanted or ()))  # endo first: outputs exist only once configured
        self.command(dq.dout(new))
        self._dout = new

    @_names_device
    def read_digital(self) -> int:
        """The seven ports D6..D0 as an int (bit n = Dn; outputs read back their switch state, p.58).
        Not scanning: ``din``. Scanning: the digital word of the newest scan (DI-1100: D1 D0 only)."""
        if self._scanning:
            if self._din_latest is None:
                raise DeviceException(f"{self.name}: no digital state in the stream yet")
            return int(self._din_latest)
        if not self.spec.digital_io:
            raise DeviceException(f"{self.name}: the {self.spec.name} has no 'din' (p.57); its D0 D1 are read "
                                  f"from the stream while scanning")
        reply = self.command(dq.din())
        try:
            return int(reply)
        except ValueError:
            raise ProtocolError(f"{self.name}: 'din' -> {reply!r} is not a number") from None

    # ---------------------------------------------------------------- analog snapshots

    def latest(self, channel: str) -> Reading | None:
        """The newest sample of a streamed channel (an immutable Reading the reader thread replaces), None
        when not streaming or not acquired."""
        if not self.running:
            return None
        return self._latest.get(channel)

    @_names_device
    def read_analog(self, channel: str) -> Reading:
        """One value of a channel: the latest sample while streaming, else a short scan (>= 20 samples,
        their mean and worst quality). The next start() restores the configuration in force before. Started and
        not stopped, its reader ended on a fatal error: that error (no scan list of one channel mid-run)."""
        if self._thread is not None and not self.running and self.error is not None:
            raise self.error.again(f"{self.name}: {channel}: no reading: the scan (not stopped) ended: {self.error}")
        if self.running:
            r = self.latest(channel)
            if r is None:
                raise DeviceException(f"{self.name}: {channel!r} is not in the running scan list")
            return r
        ch = self.profile.channel(channel)
        wanted = self._wanted
        lo, hi = self.spec.rate_bounds(1)
        self.configure(min(max(1000.0, lo), hi), [ch.name])
        self.start()
        vals, quals, raw, t = [], [], 0, time.time()
        try:
            deadline = time.monotonic() + 5 * self.profile.data_timeout_s
            while sum(v.size for v in vals) < 20 and time.monotonic() < deadline:
                b = self.get_block(timeout=2 * self.profile.data_timeout_s)
                vals.append(b.values[:, 0])
                quals.append(b.sample_quality[:, 0])
                raw, t = int(b.raw[-1, 0]), b.host_time_s
        finally:
            self.stop()
            self.config, self._wanted = None, wanted
        if not vals:
            raise DeviceTimeout(f"{self.name}: no sample of {channel!r} within {5 * self.profile.data_timeout_s:g} s")
        v, q = np.concatenate(vals), np.concatenate(quals)
        return Reading(float(np.mean(v)), ch.calibration.units, t, worst_quality(q), raw=raw)

    # ---------------------------------------------------------------- streaming

    @_names_device
    def start(self, callback: Callable[[SampleBlock], None] | None = None,
              on_error: Callable[[DeviceError], None] | None = None, *, wait_when_full: bool = False) -> float:
        """``start 0`` (never echoes, p.49) and the reader thread. Returns the exact rate.

        Blocks go to ``callback`` (in the reader thread) or to a bounded queue read by get_block. A fatal error
        ends the reader: raised by get_block, passed to on_error, kept in ``error``. Queue full: the block is
        dropped and counted (lost_before of the next one), or with wait_when_full the reader waits (the device's
        own buffer then overflows: ``stop 01``, a DeviceFault)."""
        if self._thread is not None:
            raise DeviceException(f"{self.name}: already streaming")
        if self.config is None:
            self.configure(*(self._wanted or ()))
        self._callback, self._on_error, self._wait_when_full = callback, on_error, wait_when_full
        self._queue = queue.Queue(maxsize=self.profile.queue_blocks) if callback is None else None
        self.error = self._stop_error = None
        with self._slock:
            self._stats = DataqStats()
        cfg = self.config
        self._segment, self._pending_lost, self._pending_restart = 0, 0, False
        self._stuck = [StuckDetector(int(round(c.stuck_s * cfg.rate_hz)) if c.stuck_s else 0) for c in cfg.channels]
        self._limits = quality_limits([c.calibration for c in cfg.channels])
        self._start_scan()
        self._stop_evt.clear()
        self._thread = threading.Thread(target=self._run, name=f"{self.name} reader", daemon=True)
        self._thread.start()
        return cfg.rate_hz

    def _start_scan(self) -> None:
        self._rx.clear()
        self._write(dq.start())
        self._scanning = True
        self._last_cmd = time.monotonic()
        self._decoder = dq.StreamDecoder(self.config.layout)
        self._index = 0
        self._seen_resyncs = 0
        self._silence = Silence.for_wait(self.profile.poll_s)
        self._quiet_reads = 0
        self._last_data_host = time.time()

    @_names_device
    def get_block(self, timeout: float | None = None) -> SampleBlock:
        """The next block; the reader's fatal error; DeviceTimeout if none within timeout (default data_s)."""
        if self._queue is None:
            raise DeviceException(f"{self.name}: not started in queue mode")
        timeout = self.profile.data_timeout_s if timeout is None else timeout
        try:
            item = self._queue.get(timeout=timeout)
        except queue.Empty:
            if self.error is not None:
                raise self.error from None
            if self._thread is None or not self._thread.is_alive():
                raise DeviceException(f"{self.name}: stream is stopped") from None
            raise DeviceTimeout(f"{self.name}: no sample block within {timeout:g} s") from None
        if isinstance(item, BaseException):
            raise item
        if item is None:
            raise DeviceException(f"{self.name}: stream is stopped")
        return item

    @_names_device
    def get_blocks(self) -> list[SampleBlock]:
        """Every block queued so far, without waiting (a pending fatal error is raised after the data)."""
        out = []
        while self._queue is not None:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                break
            if isinstance(item, BaseException):
                if out:
                    self._queue.put(item)
                    break
                raise item
            if item is not None:
                out.append(item)
        return out

    @_names_device
    def stop(self) -> DataqStats:
        """``stop`` (always echoes, p.50), wait for the echo, end the reader. Returns the stats; raises
        DeviceTimeout if the echo did not come (a fatal error already delivered is not raised again)."""
        t = self._thread
        if t is None:
            return self.stats
        self._stop_evt.set()
        t.join(self.profile.poll_s * 4 + 5 * self.profile.command_timeout_s + 2.0)
        alive = t.is_alive()
        self._thread = None
        self._scanning = False
        self._latest = MappingProxyType({})
        if self._queue is not None:
            try:
                self._queue.put_nowait(None)
            except queue.Full:
                pass
        if alive:
            raise DeviceTimeout(f"{self.name}: reader thread did not finish")
        if self._stop_error is not None:
            raise self._stop_error
        return self.stats

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    @property
    def stats(self) -> DataqStats:
        with self._slock:
            return replace(self._stats)

    def pressure_source(self, name: str, clock_scale: float = 1.0):
        """The PressureSource adapter (velab.drivers.pressure_source) over this DAQ."""
        from velab.drivers.dataq_source import DataqSource

        return DataqSource(self, name, clock_scale)

    # ---------------------------------------------------------------- reader thread

    def _run(self) -> None:
        prof, cfg = self.profile, self.config
        chunk = int(max(64, min(1 << 16, cfg.rate_hz * cfg.layout.scan_bytes * prof.poll_s / 2)))
        packet_s = dq.PACKET_SIZES[cfg.packet_code] / (cfg.rate_hz * cfg.layout.scan_bytes)
        try:
            while not self._stop_evt.is_set():
                try:
                    data = self._read(chunk)
                except DeviceDisconnected as exc:
                    if not prof.reconnect:
                        raise
                    self._reconnect(exc)
                    continue
                if data:
                    self._quiet_reads = 0
                    self._process(data, time.time())
                else:
                    self._quiet_reads += 1
                silent = self._silence.passed()
                if self._decoder.overflow_pending and (self._quiet_reads >= 2 and silent >= 2 * packet_s
                                                        or silent > prof.data_timeout_s):
                    raise DeviceFault(
                        f"{self.name}: the device's 1024-sample buffer overflowed ('stop 01'): it stopped scanning; "
                        f"the samples since the overflow are lost (the stream has no counter to say how many)",
                        device=self.name)
                if silent > prof.data_timeout_s:
                    d = self._decoder
                    raise StreamSilent(f"{self.name}: no in-frame scan for {prof.data_timeout_s:g} s "
                                       f"({d.skipped_total + d.skipped} bytes skipped out of frame)", device=self.name)
            self._stop_scanning()
        except DeviceError as exc:
            self._fail(exc)
        except Exception as exc:  # a bug or a callback error: still end cleanly and report
            err = DeviceError(f"{self.name}: reader failed: {type(exc).__name__}: {exc}")
            err.__cause__ = exc
            self._fail(err)
        finally:
            self._scanning = False

    def _fail(self, exc: DeviceError) -> None:
        if exc.device is None:
            exc.device = self.name
        self.error = exc
        try:  # best effort: leave the device idle
            if self._port is not None and not isinstance(exc, DeviceDisconnected):
                self._port.write(dq.stop())
        except Exception:
            pass
        if self._queue is not None:
            try:
                self._queue.put_nowait(exc)
            except queue.Full:
                try:
                    self._queue.get_nowait()
                except queue.Empty:
                    pass
                self._queue.put_nowait(exc)
        if self._on_error is not None:
            try:
                self._on_error(exc)
            except Exception:
                pass

    def _stop_scanning(self) -> None:
        """In the reader thread: ``stop``, decode what still streams, until the echo ends the bytes."""
        self._write(dq.stop())
        t_cmd = self.profile.command_timeout_s
        quiet, since = Silence.for_wait(self.profile.poll_s), Silence.for_wait(self.profile.poll_s)
        pending = bytearray()
        while True:
            over = since.passed() >= 5 * t_cmd
            expired = quiet.passed() >= t_cmd or over
            try:
                data = self._read(256)
            except DeviceDisconnected as exc:
                self._stop_error = exc
                return
            if data:
                quiet.reset()
                pending += data
                if len(pending) > 64:
                    self._process(bytes(pending[:-16]), time.time())
                    del pending[:-16]
                continue
            if pending.rstrip(b"\n\x00").endswith(dq.STOP_ECHO):
                cut = pending.rstrip(b"\n\x00")[: -len(dq.STOP_ECHO)]
                self._process(bytes(cut), time.time(), final=True)
                return
            if expired:
                why = f"within {5 * t_cmd:g} s of data" if over else f"within {t_cmd:g} s"
                self._stop_error = DeviceTimeout(f"{self.name}: no echo of 'stop' {why}")
                return

    def _reconnect(self, cause: DeviceDisconnected) -> None:
        prof = self.profile
        deadline = time.monotonic() + prof.reconnect_timeout_s
        delay, last_exc = 0.05, cause
        self._scanning = False
        last_host = self._last_data_host
        while not self._stop_evt.is_set():
            if time.monotonic() > deadline:
                raise DeviceDisconnected(f"{self.name}: disconnected and could not reconnect within "
                                         f"{prof.reconnect_timeout_s:g} s: {last_exc}", device=self.name) from cause
            self._close_port()
            time.sleep(delay)
            delay = min(delay * 2, 0.5)
            try:
                self.open()
                cfg = self.config
                self._setup(cfg.rate_hz, [c.name for c in cfg.channels])
                self._start_scan()
            except DeviceError as exc:
                last_exc = exc
                continue
            est = int(round(max(0.0, time.time() - last_host) * self.config.rate_hz))
            self._segment += 1
            self._pending_lost += est
            self._pending_restart = True
            for d in self._stuck:
                d.reset()
            with self._slock:
                self._stats.reconnects += 1
                self._stats.lost_estimated += est
            return

    def _process(self, data: bytes, host_t: float, final: bool = False) -> None:
        d = self._decoder
        chunks = d.feed(data)
        if final:
            chunks += d.flush()
        with self._slock:
            self._stats.bytes_read += len(data)
            self._stats.resyncs = d.resyncs
            self._stats.skipped_bytes = d.skipped_total
        if not chunks:
            return
        for c in chunks:
            self._emit(self._block(c, host_t))
        self._last_data_host = host_t
        self._silence.reset()  # after delivery: a slow consumer's time is not the device's silence

    def _block(self, c: dq.Chunk, host_t: float) -> SampleBlock:
        cfg, spec = self.config, self.spec
        raw = c.counts
        volts = spec.volts(raw)
        chans = cfg.channels
        signal = np.column_stack([ch.signal(volts[:, j]) for j, ch in enumerate(chans)])
        cals = [ch.calibration for ch in chans]
        lo = np.array([k.signal_lo for k in cals])
        hi = np.array([k.signal_hi for k in cals])
        vlo = np.array([k.value_lo for k in cals])
        vhi = np.array([k.value_hi for k in cals])
        zero = np.array([k.zero_offset for k in cals])
        values = vlo + (signal - lo) / (hi - lo) * (vhi - vlo) - zero
        half = 1 << (spec.adc_bits - 1)
        sq = signal_quality(signal, self._limits, clipped_hi=raw >= half - 1, clipped_lo=raw <= -half)
        for j, det in enumerate(self._stuck):
            if det.limit:
                det.flag(j, raw[:, j], sq[:, j])
        lost = c.lost_before + self._pending_lost
        restarted = self._pending_restart
        self._pending_lost, self._pending_restart = 0, False
        first = self._index + c.lost_before
        self._index = first + len(raw)
        if c.lost_before:
            with self._slock:
                self._stats.lost_estimated += c.lost_before
        if c.digital is not None and len(c.digital):
            self._din_latest = int(c.digital[-1])
        units = tuple(k.units for k in cals)
        quality = tuple(worst_quality(sq[:, j]) for j in range(len(chans)))
        rate = cfg.rate_hz
        t_last = first + len(raw) - 1
        self._latest = MappingProxyType({
            ch.name: Reading(float(values[-1, j]), units[j], host_t, QUALITY_CODES[int(sq[-1, j])],
                             device_time_s=t_last / rate, raw=int(raw[-1, j]))
            for j, ch in enumerate(chans)})
        return SampleBlock(
            segment=self._segment, first_index=first, rate_hz=rate, host_time_s=host_t, raw=raw, signal=signal,
            values=values, channels=tuple(ch.name for ch in chans), units=units, quality=quality,
            lost_before=lost, restarted=restarted, density_kg_m3=self.profile.density_kg_m3, sample_quality=sq,
            rejected_frames=c.lost_before,
        )

    def _emit(self, block: SampleBlock) -> None:
        if self._callback is None:
            try:
                self._queue.put_nowait(block)
            except queue.Full:
                while self._wait_when_full and not self._stop_evt.is_set():
                    try:
                        self._queue.put(block, timeout=self.profile.poll_s)
                        break
                    except queue.Full:
                        continue
                else:
                    self._pending_lost += block.lost_before + block.n
                    self._pending_restart |= block.restarted
                    with self._slock:
                        self._stats.queue_dropped += block.n
                    return
        else:
            self._callback(block)
        with self._slock:
            self._stats.scans += block.n
            self._stats.blocks += 1
