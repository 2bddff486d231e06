"""Serial streaming ADC (VELAB SADC-4 protocol): hardware-clocked, 1-4 channels.

Protocol: ``docs/devices-streaming-adc.md``. Parts: ``sadc_protocol`` (frame codec,
parser), ``sadc_profile`` (TOML), ``sadc_link`` (transport, commands), ``sadc_blocks``
(frames -> SampleBlocks), this module (configure, start/stop, reader thread). Qt-free.

Typical use (the recorder's view)::

    profile = load_profile("streaming_adc")          # configs/devices/streaming_adc.toml
    with StreamingADC(profile.url, profile) as adc:
        adc.configure()                              # rate, channels, ranges from the profile
        adc.start()                                  # reader thread -> bounded queue
        while recording:
            block = adc.get_block(timeout=1.0)       # SampleBlock, or a named DeviceError
        adc.stop()
        print(adc.stats)

Conditions, each named and bounded in time: corrupted frames / lost sync ->
counted, ``rejected_frames`` and ``lost_before`` on the next block; sequence gap
-> ``lost_before`` (exact); no valid frame for ``data_s`` -> StreamSilent;
disconnect -> ``condition == "reconnecting"``, then a ``restarted`` block or,
after ``reconnect_s``, DeviceDisconnected. Nothing here invents samples.
"""

from __future__ import annotations

import queue
import re
import threading
import time
from dataclasses import replace
from typing import Any, Callable

from velab.drivers.base import (  # noqa: F401 - pressure_to_head_m re-exported
    DeviceDisconnected,
    DeviceError,
    DeviceException,
    DeviceTimeout,
    ProtocolError,
    StreamSilent,
    pressure_to_head_m,
)
from velab.drivers.blocks import SampleBlock
from velab.drivers.sadc_blocks import AcquisitionConfig, BlockAssembler, StreamStats
from velab.drivers.sadc_profile import (  # noqa: F401 - re-exported
    ChannelProfile,
    StreamingADCProfile,
    StreamingADCProfileError,
    default_profile,
    load_profile,
)
from velab.drivers.sadc_protocol import *  # noqa: F401,F403 - the protocol's names, re-exported
from velab.drivers.sadc_link import SADCLink, names_device
from velab.drivers.sadc_protocol import (
    _STOP_REPLY,
    ERR_BUSY,
    MAX_BLOCK,
    MAX_CHANNELS,
    RATE_MAX_HZ,
    RATE_MIN_HZ,
    FrameParser,
    auto_block,
)
from velab.drivers.silence import Silence

CONDITIONS = ("idle", "streaming", "reconnecting", "stopped", "failed")


class StreamingADC(SADCLink):
    """Host driver for the SADC-4 streaming ADC. See the module docstring."""

    def __init__(self, transport: Any = None, profile: StreamingADCProfile | None = None, *, name: str = "streaming ADC"):
        super().__init__(transport, profile, name=name)
        self.config: AcquisitionConfig | None = None
        self._stats = StreamStats()
        self._stats_lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stop_evt = threading.Event()
        self._queue: queue.Queue | None = None
        self._callback: Callable[[SampleBlock], None] | None = None
        self._on_error: Callable[[DeviceError], None] | None = None
        self.error: DeviceError | None = None
        self._stop_error: DeviceError | None = None
        self._parser: FrameParser | None = None
        self._seg_base_stats: tuple = ()
        self._asm: BlockAssembler | None = None
        self._rejected_seen = 0
        self.condition = "idle"  # one of CONDITIONS; condition_since: time.monotonic() when it began
        self.condition_since = time.monotonic()

    def _set_condition(self, condition: str) -> None:
        if condition != self.condition:
            self.condition, self.condition_since = condition, time.monotonic()

    def close(self) -> None:
        if self._thread is not None:
            try:
                self.stop()
            except DeviceError:
                pass
        self._close_port()

    @names_device
    def configure(self, rate_hz: float | None = None, channels=None, block_samples: int | None = None) -> AcquisitionConfig:
        """Stop any stream, then set rate, channels, ranges and frame size.

        ``channels``: names or input indices (default: the profile's list).
        Returns the configuration the device accepted (actual rate from its reply).
        """
        if self._streaming:
            raise DeviceException(f"{self.name}: configure() while streaming (stop first)", ERR_BUSY)
        prof = self.profile
        rate = float(rate_hz if rate_hz is not None else prof.rate_hz)
        if not RATE_MIN_HZ <= rate <= RATE_MAX_HZ:
            raise ValueError(f"rate_hz must be {RATE_MIN_HZ}..{RATE_MAX_HZ}, got {rate}")
        keys = channels if channels is not None else prof.enabled
        chans = sorted({prof.channel(k).index: prof.channel(k) for k in keys}.values(), key=lambda c: c.index)
        if not 1 <= len(chans) <= MAX_CHANNELS:
            raise ValueError("acquire 1 to 4 channels")
        block = block_samples if block_samples is not None else prof.block_samples
        if not block:
            block = auto_block(rate, len(chans))
        if not 1 <= block <= MAX_BLOCK:
            raise ValueError(f"block_samples must be 1..{MAX_BLOCK}")
        self.open()
        self._stop_idle()
        reply = self.command(f"RATE {rate:.10g}")
        try:
            actual = float(reply.split()[1])
        except (IndexError, ValueError):
            raise ProtocolError(f"{self.name}: 'RATE' -> unexpected reply 'OK {reply}'") from None
        self.command("CHAN " + ",".join(str(c.index) for c in chans))
        for c in chans:
            self.command(f"RANGE {c.index} {c.range}")
        self.command(f"BLOCK {block}")
        self.config = AcquisitionConfig(actual, tuple(chans), block)
        return self.config

    # ---------------------------------------------------------------- streaming

    @names_device
    def start(self, callback: Callable[[SampleBlock], None] | None = None,
              on_error: Callable[[DeviceError], None] | None = None, *, wait_when_full: bool = False) -> None:
        """Start the stream and the reader thread.

        With ``callback`` each SampleBlock is passed to it (in the reader thread,
        keep it short); otherwise blocks go to a bounded queue read with
        :meth:`get_block`. A fatal error (DeviceTimeout, DeviceDisconnected after
        failed reconnection, ...) ends the reader; it is raised by ``get_block``
        and passed to ``on_error``, and kept in ``self.error``.

        Queue full (the consumer is too slow): by default the block is dropped,
        counted in ``stats.queue_dropped`` and reported as ``lost_before`` of the
        next block. With ``wait_when_full=True`` the reader waits instead, so the
        back-pressure reaches the device, whose FIFO overrun is then counted
        exactly from its sample counter.
        """
        if self._thread is not None:
            raise DeviceException(f"{self.name}: already streaming", ERR_BUSY)
        if self.config is None:
            self.configure()
        self._callback = callback
        self._on_error = on_error
        self._wait_when_full = wait_when_full
        self._queue = queue.Queue(maxsize=self.profile.queue_blocks) if callback is None else None
        self.error = None
        self._stop_error = None
        self._stop_backlog = 0  # bytes received before STOP went out still to read (the reader's, at stop())
        with self._stats_lock:
            self._stats = StreamStats()
        self._asm = BlockAssembler(self.config, self.profile, self._stats, self._stats_lock)
        self._start_stream()
        self._stop_evt.clear()
        self._thread = threading.Thread(target=self._run, name=f"{self.name} reader", daemon=True)
        self._thread.start()

    def _start_stream(self) -> None:
        self.command("START")
        cfg = self.config
        self._parser = FrameParser(cfg.mask, cfg.block_samples)
        self._rejected_seen = 0
        self._streaming = True
        self._set_condition("streaming")
        self._silence = Silence.for_wait(self.profile.poll_s)
        self._last_frame_host = time.time()
        self._seg_base_stats = (0, 0, 0, 0)

    @names_device
    def get_block(self, timeout: float | None = None) -> SampleBlock:
        """Next block from the queue. Raises the reader's fatal error, or
        DeviceTimeout if nothing arrives within ``timeout`` (default: data timeout)."""
        if self._queue is None:
            raise DeviceException(f"{self.name}: not started in queue mode")
        timeout = self.profile.data_timeout_s if timeout is None else timeout
        try:
            item = self._queue.get(timeout=timeout)
        except queue.Empty:
            if self.error is not None:
                raise self.error
            if self._thread is None or not self._thread.is_alive():
                raise DeviceException(f"{self.name}: stream is stopped")
            since = time.monotonic() - self.condition_since
            raise DeviceTimeout(f"{self.name}: no sample block within {timeout:g} s "
                                f"({self.condition} for {since:.1f} s)") from None
        if isinstance(item, BaseException):
            raise item
        if item is None:
            raise DeviceException(f"{self.name}: stream is stopped")
        return item

    @names_device
    def get_blocks(self) -> list[SampleBlock]:
        """Every block queued so far, without waiting (raises a pending fatal error)."""
        out = []
        while self._queue is not None:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                break
            if isinstance(item, BaseException):
                if out:  # deliver data first; keep the error for the next call
                    self._queue.put(item)
                    break
                raise item
            if item is not None:
                out.append(item)
        return out

    @names_device
    def stop(self) -> StreamStats:
        """Stop the stream (STOP, wait for its acknowledgement, count the tail) and the reader.

        Returns the final stats. Raises DeviceTimeout if the device did not
        acknowledge STOP; a fatal error that already ended the reader is not
        raised again (it was delivered, and stays in ``self.error``).
        """
        t = self._thread
        if t is None:
            return self.stats
        self._stop_evt.set()
        bound = self.profile.poll_s * 4 + 5 * self.profile.command_timeout_s + 2.0  # _stop_streaming's bound ...
        deadline, left = time.monotonic() + bound, 0
        while t.is_alive() and time.monotonic() < deadline:
            t.join(min(0.1, max(0.0, deadline - time.monotonic())))
            now_left = self._stop_backlog
            if 0 < now_left != left:  # ... counted once the bytes received before STOP are read (while reads take them)
                deadline, left = time.monotonic() + bound, now_left
        alive = t.is_alive()
        self._thread = None
        self._streaming = False
        if self.condition != "failed":
            self._set_condition("stopped")
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
    def stats(self) -> StreamStats:
        with self._stats_lock:
            s = replace(self._stats)
        p = getattr(self, "_parser", None)
        if p is not None and self._seg_base_stats:
            b = self._seg_base_stats
            s.crc_errors += p.crc_errors - b[0]
            s.header_errors += p.header_errors - b[1]
            s.resyncs += p.resyncs - b[2]
            s.discarded_bytes += p.discarded_bytes - b[3]
        return s

    # ---------------------------------------------------------------- reader thread

    def _run(self) -> None:
        prof = self.profile
        cfg = self.config
        # read about half a poll period of data per call (at least a frame): big blocks, bounded latency
        per_s = cfg.rate_hz / cfg.block_samples * cfg.frame_len
        chunk = int(max(cfg.frame_len, min(1 << 16, per_s * prof.poll_s / 2)))
        try:
            if self._rx:  # bytes that followed the START reply
                data, self._rx = bytes(self._rx), bytearray()
                self._process(data, time.time())
            while not self._stop_evt.is_set():
                try:
                    data = self._read(chunk)
                except DeviceDisconnected as exc:
                    if not prof.reconnect:
                        raise
                    self._reconnect(exc)
                    continue
                if data:
                    self._process(data, time.time())
                if self._silence.passed() > prof.data_timeout_s:
                    p = self._parser
                    raise StreamSilent(
                        f"{self.name}: no valid frame for {prof.data_timeout_s:g} s "
                        f"({p.crc_errors} CRC errors, {p.discarded_bytes} bytes discarded)", device=self.name)
            self._stop_streaming()
        except DeviceError as exc:
            self._fail(exc)
        except Exception as exc:  # a bug or a callback error: still end cleanly and report
            err = DeviceError(f"{self.name}: reader failed: {type(exc).__name__}: {exc}")
            err.__cause__ = exc
            self._fail(err)
        finally:
            self._streaming = False

    def _fail(self, exc: DeviceError) -> None:
        if exc.device is None:
            exc.device = self.name
        self.error = exc
        self._set_condition("failed")
        try:  # best effort: leave the device idle
            if self._port is not None and not isinstance(exc, DeviceDisconnected):
                self._port.write(b"STOP\n")
        except Exception:
            pass
        if self._queue is not None:
            try:
                self._queue.put_nowait(exc)
            except queue.Full:  # make room: the error matters more than the oldest block
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

    def _stop_streaming(self) -> None:
        """In the reader thread: send STOP, keep parsing frames until ``OK STOP <n>``."""
        self._write(b"STOP\n")
        # what had been received when STOP went out, the device sent before it could see STOP: parsing it says
        # nothing of a device that streams on, so the bound on frames starts once it is read (a loaded host held
        # ~1 MB of frames on a TCP link, more than 5 s of its parsing: "no reply to 'STOP' within 5 s of frames")
        backlog = self._stop_backlog = self._received()
        t_cmd = self.profile.command_timeout_s
        hard = 5 * t_cmd  # frames still in flight are parsed, within bounds
        # both in the time this thread listened (velab.drivers.silence): a pass the host held it longer than a
        # poll counts a poll's worth (a loaded pair's unpaced simulator, in the same process, answered STOP after
        # such a pass: "no reply to 'STOP' within 1 s")
        quiet, since_stop = Silence.for_wait(self.profile.poll_s), Silence.for_wait(self.profile.poll_s)
        final = False
        while not final:
            # once the time is up, one more read: what came while this thread was not running (a slow consumer
            # of the last frames, a loaded host) is still the device's answer; that look is the last unless it
            # brought bytes before the hard bound
            if backlog > 0:
                since_stop.reset()
            over = since_stop.passed() >= hard
            expired = quiet.passed() >= t_cmd or over
            try:  # (the backlog in big reads: a frame a pass took seconds on a loaded host)
                data = self._read(max(self.config.frame_len, min(backlog, 1 << 16)))
            except DeviceDisconnected as exc:
                self._stop_error = exc
                return
            backlog -= len(data)
            self._stop_backlog = max(0, backlog)
            final = expired and (not data or over)
            if data:
                quiet.reset()
                total = self._process(data, time.time(), stopping=True)
                if total is not None:
                    tail = total - self._asm.expected
                    if tail > 0:
                        with self._stats_lock:
                            self._stats.lost += tail
                        self._asm.expected = total
                    return
        m = _STOP_REPLY.search(self._parser.buf)
        if m:
            tail = int(m.group(1)) - self._asm.expected
            if tail > 0:
                with self._stats_lock:
                    self._stats.lost += tail
            return
        why = f"within {hard:g} s of frames" if over else f"within {t_cmd:g} s of the device's silence"
        self._stop_error = DeviceTimeout(f"{self.name}: no reply to 'STOP' {why}")

    def _reconnect(self, cause: DeviceDisconnected) -> None:
        prof = self.profile
        deadline = time.monotonic() + prof.reconnect_timeout_s
        delay = 0.05
        last_exc: Exception = cause
        self._streaming = False
        p = self._parser
        b = self._seg_base_stats
        with self._stats_lock:  # fold this segment's parser counters into the stats
            self._stats.crc_errors += p.crc_errors - b[0]
            self._stats.header_errors += p.header_errors - b[1]
            self._stats.resyncs += p.resyncs - b[2]
            self._stats.discarded_bytes += p.discarded_bytes - b[3]
        self._seg_base_stats = ()
        last_host = self._last_frame_host
        self._set_condition("reconnecting")
        while not self._stop_evt.is_set():
            if time.monotonic() > deadline:
                raise DeviceDisconnected(
                    f"{self.name}: disconnected and could not reconnect within {prof.reconnect_timeout_s:g} s: {last_exc}",
                    device=self.name) from cause
            self._close_port()
            time.sleep(delay)
            delay = min(delay * 2, 0.5)
            try:
                self.open()
                cfg = self.config
                self.configure(cfg.rate_hz, [c.index for c in cfg.channels], cfg.block_samples)
                self._start_stream()
            except (DeviceError, ProtocolError) as exc:
                last_exc = exc
                continue
            gap_s = max(0.0, time.time() - last_host)
            est = int(round(gap_s * self.config.rate_hz))
            self._asm.new_segment(est)
            with self._stats_lock:
                self._stats.reconnects += 1
                self._stats.lost_estimated += est
            if self._rx:
                data, self._rx = bytes(self._rx), bytearray()
                self._process(data, time.time())
            return
        self._streaming = False

    def _process(self, data: bytes, host_t: float, stopping: bool = False) -> int | None:
        """Parse bytes, build and deliver blocks. Returns the STOP total if its reply was seen."""
        p = self._parser
        frames, lines = p.feed(data)
        stop_total = None
        for ln in lines:
            m = re.match(r"OK STOP (\d+)$", ln)
            if m and stopping:
                stop_total = int(m.group(1))
        with self._stats_lock:
            self._stats.bytes_read += len(data)
        rejected = p.crc_errors + p.header_errors
        if rejected != self._rejected_seen:
            self._asm.pending_rejected += rejected - self._rejected_seen
            self._rejected_seen = rejected
        if frames:
            self._last_frame_host = host_t
            for b in self._asm.frames(frames, host_t):
                self._emit(b)
            # after the delivery: the data timeout counts the device's silence, not the time a slow consumer
            # (the callback, a full queue) held the reader (a loaded host's run failed "no valid frame")
            self._silence.reset()
        return stop_total

    def _emit(self, block: SampleBlock) -> None:
        if self._callback is not None:
            self._callback(block)
            with self._stats_lock:
                self._stats.samples += block.n
                self._stats.blocks += 1
            return
        try:
            self._queue.put_nowait(block)
        except queue.Full:
            while self._wait_when_full and not self._stop_evt.is_set():
                try:
                    self._queue.put(block, timeout=self.profile.poll_s)
                except queue.Full:
                    continue
                with self._stats_lock:
                    self._stats.samples += block.n
                    self._stats.blocks += 1
                return
            # the consumer is too slow: drop this block, report it as a gap on the next one
            self._asm.pending_lost += block.lost_before + block.n
            self._asm.pending_rejected += block.rejected_frames
            self._asm.pending_restart |= block.restarted
            with self._stats_lock:
                self._stats.queue_dropped += block.n
            return
        with self._stats_lock:
            self._stats.samples += block.n
            self._stats.blocks += 1


__all__ = [
    "AcquisitionConfig", "CONDITIONS", "ChannelProfile", "Frame", "FrameParser", "SampleBlock", "StreamStats",
    "StreamingADC", "StreamingADCProfile", "StreamingADCProfileError", "actual_rate", "auto_block",
    "channel_mask", "crc16", "default_profile", "encode_frame", "frame_length", "load_profile", "mask_channels",
]
