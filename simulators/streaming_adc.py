"""Simulated SADC-4 streaming ADC: the device side of docs/devices-streaming-adc.md.

Serves the exact wire protocol of :mod:`velab.drivers.streaming_adc` over

* a TCP listener on 127.0.0.1 (``socket://127.0.0.1:PORT``; port 0 = ephemeral), or
* a pty: the simulator owns the master side and publishes a stable symlink to
  the slave (``/tmp/.../sadc``), re-pointed after an injected disconnect, like a
  udev name for a USB-serial device that is unplugged and plugged back.

The analogue inputs come from ``source(t) -> (n, 4)`` in mA (the interface of
``velab.simulators.rig.SimulatedRig.analog_inputs``; pass ``clock=`` to put the
device time on that clock's axis: t = clock.now() at START + i / fs); they are quantised to the
ADC's int16 counts. Pacing: ``realtime=True`` emits frames when the device clock
says they are due; ``realtime=False`` (fast mode) streams as fast as the reader
consumes, the device clock still advancing by 1/fs per sample. ``baud`` adds the
wire time of 10 bits per byte. Fault injection through :class:`FaultPlan`; every
sample the simulator generated but did not deliver intact is counted in
``stats.samples_lost`` so tests can compare it with the driver's count.

Run standalone: ``python -m velab.simulators.streaming_adc --tcp 0 [--fast]``.
"""

from __future__ import annotations

import argparse
import errno
import math
import os
import select
import socket
import tempfile
import threading
import time
import tty
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from velab.drivers.streaming_adc import (
    ERR_BAD_ARGUMENT,
    ERR_BUSY,
    ERR_LINE_TOO_LONG,
    ERR_LINK_TOO_SLOW,
    ERR_UNKNOWN_COMMAND,
    ERROR_NAMES,
    FLAG_CLIP,
    FLAG_INVALID,
    FLAG_OVERRUN,
    MAX_BLOCK,
    MAX_CHANNELS,
    MAX_LINE,
    RANGES_FS,
    RATE_MAX_HZ,
    RATE_MIN_HZ,
    RAW_FULL_SCALE,
    RAW_INVALID,
    actual_rate,
    channel_mask,
    encode_frame,
    frame_length,
)

Source = Callable[[np.ndarray], np.ndarray]


def default_source(t: np.ndarray) -> np.ndarray:
    """4 analogue inputs in mA: a pressure-like 12 +/- 4 mA oscillation with a step at
    t = 1 s, a valve position ramp 20 -> 4 mA over 0.15 s at t = 1 s, 4 mA and 12 mA spares."""
    t = np.asarray(t, dtype=float)
    out = np.empty((t.size, 4))
    step = t >= 1.0
    out[:, 0] = 10.0 + 4.0 * step * np.exp(-(t - 1.0).clip(0) * 0.5) * np.cos(2 * np.pi * 2.5 * (t - 1.0))
    out[:, 1] = 20.0 - 16.0 * np.clip((t - 1.0) / 0.15, 0.0, 1.0)
    out[:, 2] = 4.0
    out[:, 3] = 12.0
    return out


def sine_source(mean_ma: float = 12.0, amp_ma: float = 4.0, freq_hz: float = 5.0) -> Source:
    def source(t: np.ndarray) -> np.ndarray:
        s = mean_ma + amp_ma * np.sin(2 * np.pi * freq_hz * np.asarray(t, dtype=float))
        return np.repeat(s[:, None], 4, axis=1)

    return source


def ramp_source(t: np.ndarray) -> np.ndarray:
    """Counts-exact test signal: channel c carries (index mod 1000) * 0.01 mA + c mA,
    with index = round(t * 10 kHz); handy to check that no sample was invented."""
    i = np.rint(np.asarray(t, dtype=float) * 10_000.0) % 1000
    return np.stack([4.0 + i * 0.01 + c for c in range(4)], axis=1)


@dataclass
class FaultPlan:
    """Faults to inject. Frame numbers count frames generated since START (0-based)."""

    corrupt_frames: frozenset = frozenset()  # flip one byte in these frames
    corrupt_every: int = 0  # ... and in every Nth frame (N-1, 2N-1, ...)
    drop_frames: frozenset = frozenset()  # never send these (sequence gap)
    drop_every: int = 0
    drop_bytes_frames: frozenset = frozenset()  # remove 3 bytes from inside these frames
    drop_bytes_every: int = 0
    garbage_every: int = 0  # insert 3..40 junk bytes (with fake sync) after every Nth frame
    overrun_at: frozenset = frozenset()  # the FIFO overflows here: discard `overrun_frames` frames
    overrun_frames: int = 5
    silent_after_frames: int | None = None  # then send nothing more (no frames, no replies)
    disconnect_after_frames: int | None = None  # then drop the link (TCP close / pty vanishes)
    disconnects: int = 1  # how many times disconnect_after_frames fires
    reconnect_delay_s: float = 0.2  # the link is unavailable this long after a disconnect
    input_faults: tuple = ()  # (channel, t_start_s, t_end_s, value_mA); NaN allowed
    seed: int = 1

    def set(self, **kw) -> "FaultPlan":
        """Change faults by name (the SimulatedBench's [faults.<device>] hook)."""
        for k, v in kw.items():
            if k not in self.__dataclass_fields__:
                raise ValueError(f"unknown streaming ADC fault {k!r} (known: {', '.join(self.__dataclass_fields__)})")
            setattr(self, k, frozenset(v) if isinstance(getattr(self, k), frozenset) else v)
        return self

    @staticmethod
    def _hit(n: int, frames: frozenset, every: int) -> bool:
        return n in frames or (every > 0 and n % every == every - 1)


@dataclass
class SimStats:
    connections: int = 0
    starts: int = 0
    commands: int = 0
    frames_generated: int = 0
    frames_sent: int = 0
    samples_generated: int = 0  # per channel
    samples_lost: int = 0  # generated but not delivered intact (every fault reason)
    frames_corrupted: int = 0
    frames_dropped: int = 0
    frames_bytes_dropped: int = 0
    frames_overrun: int = 0
    garbage_bytes: int = 0
    disconnects: int = 0
    last_stop_total: int = 0


class _Link:
    """A selectable byte pipe: a connected TCP socket or a pty master fd."""

    def __init__(self, fd: int, sock: socket.socket | None = None):
        self.fd = fd
        self.sock = sock

    def recv(self) -> bytes | None:
        try:
            data = self.sock.recv(65536) if self.sock else os.read(self.fd, 65536)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError as exc:
            if self.sock is None and exc.errno == errno.EIO:  # no slave open right now
                return b""
            return None
        if self.sock is not None and not data:
            return None
        return data

    def send(self, data) -> int:
        try:
            return self.sock.send(data) if self.sock else os.write(self.fd, data)
        except (BlockingIOError, InterruptedError):
            return 0
        except OSError:
            return -1

    def close(self) -> None:
        try:
            if self.sock is not None:
                self.sock.close()
            else:
                os.close(self.fd)
        except OSError:
            pass


class StreamingADCSimulator:
    """The simulated device. ``serve_tcp()`` or ``serve_pty()``, then ``close()``."""

    IDN = "VELAB,SADC-4"

    def __init__(
        self,
        source: Source | None = None,
        *,
        realtime: bool = True,
        baud: int | None = None,
        faults: FaultPlan | None = None,
        serial_no: str = "SIM0001",
        firmware: str = "1.0",
        fifo_frames: int = 64,
        fast_backlog_bytes: int = 1 << 16,
        clock=None,
    ):
        self.source = source or default_source
        self.realtime = realtime
        self.baud = baud
        self.faults = faults or FaultPlan()
        self.serial_no = serial_no
        self.firmware = firmware
        self.fifo_frames = fifo_frames
        self.fast_backlog_bytes = fast_backlog_bytes
        self.clock = clock  # optional: source time = clock.now() at START + device time
        self._t_source0 = 0.0
        self.stats = SimStats()
        self.url: str | None = None
        self.pty_link: str | None = None
        self.slave_name: str | None = None
        self._closing = threading.Event()
        self._threads: list[threading.Thread] = []
        self._listener: socket.socket | None = None
        self._rng = np.random.default_rng(self.faults.seed)
        self._disconnects_left = self.faults.disconnects
        self._reset_config()
        self.running = False

    # ------------------------------------------------------------ device state

    def _reset_config(self) -> None:
        self.rate_hz = 1000.0
        self.channels = [0]
        self.ranges = ["25MA"] * MAX_CHANNELS
        self.block = 10
        self.running = False

    def _handle_line(self, line: bytes) -> str | None:
        self.stats.commands += 1
        try:
            text = line.decode("ascii")
        except UnicodeDecodeError:
            return self._err(ERR_UNKNOWN_COMMAND)
        tokens = text.split(" ")
        cmd, args = tokens[0], tokens[1:]
        if self.running and cmd not in ("STOP", "*IDN?"):
            return self._err(ERR_BUSY, "stop first")
        if cmd == "*IDN?" and not args:
            return f"OK {self.IDN},{self.serial_no},{self.firmware}"
        if cmd == "RST" and not args:
            self._reset_config()
            return "OK RST"
        if cmd == "RATE" and len(args) == 1:
            try:
                hz = float(args[0])
            except ValueError:
                return self._err(ERR_BAD_ARGUMENT, "rate is not a number")
            if not (RATE_MIN_HZ <= hz <= RATE_MAX_HZ) or not math.isfinite(hz):
                return self._err(ERR_BAD_ARGUMENT, f"rate must be {RATE_MIN_HZ}..{RATE_MAX_HZ}")
            self.rate_hz = actual_rate(hz)
            return f"OK RATE {_fmt_rate(self.rate_hz)}"
        if cmd == "CHAN" and len(args) == 1:
            try:
                chans = [int(x) for x in args[0].split(",")]
            except ValueError:
                return self._err(ERR_BAD_ARGUMENT, "channel list")
            if not chans or len(set(chans)) != len(chans) or any(not 0 <= c < MAX_CHANNELS for c in chans):
                return self._err(ERR_BAD_ARGUMENT, "channels must be distinct 0..3")
            self.channels = sorted(chans)
            return "OK CHAN " + ",".join(map(str, self.channels))
        if cmd == "RANGE" and len(args) == 2:
            if args[0] not in ("0", "1", "2", "3") or args[1] not in RANGES_FS:
                return self._err(ERR_BAD_ARGUMENT, "RANGE <0..3> <" + "|".join(RANGES_FS) + ">")
            self.ranges[int(args[0])] = args[1]
            return f"OK RANGE {args[0]} {args[1]}"
        if cmd == "BLOCK" and len(args) == 1:
            if not args[0].isdigit() or not 1 <= int(args[0]) <= MAX_BLOCK:
                return self._err(ERR_BAD_ARGUMENT, f"block must be 1..{MAX_BLOCK}")
            self.block = int(args[0])
            return f"OK BLOCK {self.block}"
        if cmd == "START" and not args:
            flen = frame_length(len(self.channels), self.block)
            need = self.rate_hz / self.block * flen * 10
            if self.baud and need > self.baud:
                return self._err(ERR_LINK_TOO_SLOW, f"needs {need:.0f} baud")
            self._begin_stream()
            return "OK START"
        if cmd == "STOP" and not args:
            self.running = False
            self.stats.last_stop_total = self.index
            return f"OK STOP {self.index}"
        known = cmd in ("*IDN?", "RST", "RATE", "CHAN", "RANGE", "BLOCK", "START", "STOP")
        return self._err(ERR_BAD_ARGUMENT, "wrong number of arguments") if known else self._err(ERR_UNKNOWN_COMMAND)

    @staticmethod
    def _err(code: int, detail: str = "") -> str:
        return f"ERR {code} {ERROR_NAMES[code]}" + (f": {detail}" if detail else "")

    def _begin_stream(self) -> None:
        self.running = True
        self.index = 0
        self.frame_no = 0
        self.t_start = time.monotonic()
        self._t_source0 = float(self.clock.now()) if self.clock is not None else 0.0
        self.mask = channel_mask(self.channels)
        self.fs_counts = np.array([RAW_FULL_SCALE / RANGES_FS[self.ranges[c]][0] for c in self.channels])
        self.frame_len = frame_length(len(self.channels), self.block)
        self._overrun_left = 0
        self._flag_overrun = False
        self.stats.starts += 1

    index = 0
    frame_no = 0

    def _quantise(self, t: np.ndarray) -> np.ndarray:
        sig = np.asarray(self.source(t + self._t_source0), dtype=float)[:, self.channels]
        for ch, t0, t1, val in self.faults.input_faults:
            if ch in self.channels:
                sel = (t >= t0) & (t < t1)
                sig[sel, self.channels.index(ch)] = val
        counts = np.rint(sig * self.fs_counts)
        bad = ~np.isfinite(counts)
        counts = np.clip(np.where(bad, 0, counts), -RAW_FULL_SCALE, RAW_FULL_SCALE)
        counts[bad] = RAW_INVALID
        return counts.astype("<i2")

    def _generate(self, n_frames: int, out: bytearray, fifo_limit: int | None) -> int:
        """Make the next n_frames frames (device clock advances for every one of them)."""
        f = self.faults
        k = self.block
        for limit in (f.silent_after_frames, f.disconnect_after_frames if self._disconnects_left > 0 else None):
            if limit is not None:
                n_frames = min(n_frames, limit - self.frame_no)  # stop exactly at the fault point
        if n_frames <= 0:
            return 0
        t = (self.index + np.arange(n_frames * k)) / self.rate_hz
        counts = self._quantise(t).reshape(n_frames, k, len(self.channels))
        st = self.stats
        for j in range(n_frames):
            n = self.frame_no
            first = self.index
            self.frame_no += 1
            self.index += k
            st.frames_generated += 1
            st.samples_generated += k
            if n in f.overrun_at:
                self._overrun_left = f.overrun_frames
            if self._overrun_left > 0 or (fifo_limit is not None and len(out) + self.frame_len > fifo_limit):
                self._overrun_left = max(0, self._overrun_left - 1)
                self._flag_overrun = True
                st.frames_overrun += 1
                st.samples_lost += k
                continue
            if FaultPlan._hit(n, f.drop_frames, f.drop_every):
                st.frames_dropped += 1
                st.samples_lost += k
                continue
            raw = counts[j]
            flags = FLAG_OVERRUN if self._flag_overrun else 0
            self._flag_overrun = False
            if (raw == RAW_INVALID).any():
                flags |= FLAG_INVALID
            if (np.abs(raw) == RAW_FULL_SCALE).any():
                flags |= FLAG_CLIP
            frame = bytearray(encode_frame(n, first, self.mask, raw, flags))
            if FaultPlan._hit(n, f.corrupt_frames, f.corrupt_every):
                pos = int(self._rng.integers(0, len(frame)))
                frame[pos] ^= int(self._rng.integers(1, 256))
                st.frames_corrupted += 1
                st.samples_lost += k
            elif FaultPlan._hit(n, f.drop_bytes_frames, f.drop_bytes_every):
                pos = int(self._rng.integers(2, len(frame) - 3))
                del frame[pos : pos + 3]
                st.frames_bytes_dropped += 1
                st.samples_lost += k
            out += frame
            st.frames_sent += 1
            if f.garbage_every and n % f.garbage_every == f.garbage_every - 1:
                junk = bytearray(self._rng.integers(0, 256, int(self._rng.integers(3, 41)), dtype=np.uint8).tobytes())
                junk[0:2] = b"\xa5\x5a"
                out += junk
                st.garbage_bytes += len(junk)
        return n_frames

    # ------------------------------------------------------------ one connection

    def _session(self, link: _Link) -> str:
        """Serve one link until it closes ('closed'), a disconnect fault ('disconnect') or close()."""
        f = self.faults
        self.stats.connections += 1
        inbuf = bytearray()
        out = bytearray()
        silent = False
        allowance = 0.0
        last = time.monotonic()
        while not self._closing.is_set():
            now = time.monotonic()
            # ---- produce frames
            timeout = 0.05
            if self.running and not silent:
                if self.realtime:
                    # paced by the device clock: the simulation clock if one was given
                    # (one time base with the rig, possibly faster than real time)
                    dev_now = (self.clock.now() - self._t_source0) if self.clock is not None else now - self.t_start
                    due = int(dev_now * self.rate_hz) // self.block - self.frame_no
                    if due > 0:
                        self._generate(min(due, 4096), out, self.fifo_frames * self.frame_len)
                    if self.clock is not None:
                        scale = getattr(self.clock, "scale", 1.0)
                        wait = ((self.frame_no + 1) * self.block / self.rate_hz - (self.clock.now() - self._t_source0)) / scale
                    else:
                        wait = self.t_start + (self.frame_no + 1) * self.block / self.rate_hz - time.monotonic()
                    timeout = min(timeout, max(0.0, wait))
                elif len(out) < self.fast_backlog_bytes:
                    room = (self.fast_backlog_bytes - len(out)) // self.frame_len
                    if self._generate(max(1, min(room, 64)), out, None):
                        timeout = 0.0
                if f.silent_after_frames is not None and self.frame_no >= f.silent_after_frames and not out:
                    silent = True  # everything before the fault point was sent; now nothing more
                if (f.disconnect_after_frames is not None and self._disconnects_left > 0
                        and self.frame_no >= f.disconnect_after_frames and not out):
                    self._disconnects_left -= 1
                    self.stats.disconnects += 1
                    return "disconnect"  # what is still in `out` never reaches the host
            # ---- wire pacing
            if self.baud:
                allowance = min(allowance + (now - last) * self.baud / 10.0, 4096.0)
                last = now
                if out and allowance < 1.0:
                    timeout = min(timeout, 10.0 / self.baud)
            wants_write = bool(out) and (not self.baud or allowance >= 1.0)
            try:
                r, w, _ = select.select([link.fd], [link.fd] if wants_write else [], [], timeout)
            except (OSError, ValueError):
                return "closed"
            if r:
                data = link.recv()
                if data is None:
                    return "closed"
                inbuf += data
                while True:
                    nl = inbuf.find(b"\n")
                    if nl < 0:
                        if len(inbuf) >= MAX_LINE:
                            inbuf.clear()
                            if not silent:
                                out += (self._err(ERR_LINE_TOO_LONG) + "\n").encode()
                        break
                    line = bytes(inbuf[:nl]).replace(b"\r", b"")
                    del inbuf[: nl + 1]
                    if len(line) >= MAX_LINE:
                        reply = self._err(ERR_LINE_TOO_LONG)
                    elif not line:
                        continue
                    else:
                        reply = self._handle_line(line)
                    if reply is not None and not silent:
                        out += reply.encode("ascii") + b"\n"
            if w and out:
                n = len(out) if not self.baud else min(len(out), int(allowance))
                sent = link.send(memoryview(out)[: min(n, 65536)])
                if sent < 0:
                    return "closed"
                if self.baud:
                    allowance -= sent
                del out[:sent]
        return "closed"

    # ------------------------------------------------------------ TCP

    def serve_tcp(self, host: str = "127.0.0.1", port: int = 0) -> str:
        """Listen on host:port (0 = ephemeral); returns the ``socket://`` URL."""
        ls = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        ls.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        ls.bind((host, port))
        ls.listen(1)
        ls.settimeout(0.1)
        self._listener = ls
        self.url = f"socket://{host}:{ls.getsockname()[1]}"
        self._spawn(self._tcp_loop)
        return self.url

    def _tcp_loop(self) -> None:
        ls = self._listener
        while not self._closing.is_set():
            try:
                conn, _ = ls.accept()
            except socket.timeout:
                continue
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn.setblocking(False)
            link = _Link(conn.fileno(), conn)
            why = self._session(link)
            link.close()
            self._reset_config()  # a power-cycled / re-plugged device comes back idle
            if why == "disconnect":
                self._unavailable(ls)

    def _unavailable(self, ls: socket.socket) -> None:
        """Refuse connections for reconnect_delay_s (clients queued meanwhile are dropped)."""
        end = time.monotonic() + self.faults.reconnect_delay_s
        while time.monotonic() < end and not self._closing.is_set():
            try:
                c, _ = ls.accept()
                c.close()
            except socket.timeout:
                pass
            except OSError:
                return

    # ------------------------------------------------------------ pty

    def serve_pty(self, link_path: str | None = None) -> str:
        """Create a pty; returns a stable symlink to its slave (open it with the driver)."""
        self._own_dir = link_path is None
        if link_path is None:
            link_path = os.path.join(tempfile.mkdtemp(prefix="velab-sadc-"), "sadc")
        os.makedirs(os.path.dirname(os.path.abspath(link_path)), exist_ok=True)
        self.pty_link = link_path
        self._master, self._slave = self._new_pty()
        self.url = link_path
        self._spawn(self._pty_loop)
        return link_path

    def _new_pty(self) -> tuple[int, int]:
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        self.slave_name = os.ttyname(slave)
        tmp = self.pty_link + ".new"
        if os.path.lexists(tmp):
            os.unlink(tmp)
        os.symlink(self.slave_name, tmp)
        os.replace(tmp, self.pty_link)
        return master, slave

    def _pty_loop(self) -> None:
        while not self._closing.is_set():
            link = _Link(self._master)
            why = self._session(link)
            if self._closing.is_set():
                break
            if why == "disconnect":
                os.unlink(self.pty_link)  # the device node vanishes ...
                link.close()
                os.close(self._slave)
                self._reset_config()
                self._closing.wait(self.faults.reconnect_delay_s)
                self._master, self._slave = self._new_pty()  # ... and comes back
            else:
                time.sleep(0.01)

    # ------------------------------------------------------------ lifecycle

    def _spawn(self, target) -> None:
        t = threading.Thread(target=target, name="sadc-sim", daemon=True)
        self._threads.append(t)
        t.start()

    def close(self) -> None:
        self._closing.set()
        if self._listener is not None:
            try:
                self._listener.close()
            except OSError:
                pass
        for t in self._threads:
            t.join(2.0)
        if self.pty_link is not None:
            for fd in (getattr(self, "_master", None), getattr(self, "_slave", None)):
                if fd is not None:
                    try:
                        os.close(fd)
                    except OSError:
                        pass
            try:
                os.unlink(self.pty_link)
                if self._own_dir:
                    os.rmdir(os.path.dirname(self.pty_link))
            except OSError:
                pass

    def __enter__(self) -> "StreamingADCSimulator":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ---------------------------------------------------------------- `velab sim` registration


class StreamingADCSimHandle:
    """The streaming ADC as a SimulatedBench device (``kind = "streaming_adc"``).

    Config keys: ``endpoints`` = list of ``{transport = "socket", port = N}`` /
    ``{transport = "pty", link = "/tmp/velab-sim/sadc"}``; ``realtime`` (default
    true); ``baudrate`` (adds wire time); ``serial_no``. The analogue inputs are
    the rig's ``analog_inputs`` on the rig's clock.
    """

    KEYS = {"kind", "endpoints", "realtime", "baudrate", "serial_no", "profile"}

    def __init__(self, name: str, rig, cfg: dict, host: str):
        from velab.errors import ConfigError

        unknown = sorted(set(cfg) - self.KEYS)
        if unknown:
            raise ConfigError(f"[devices.{name}] {unknown[0]}: unknown key (known: {', '.join(sorted(self.KEYS))})")
        self.name, self.rig, self.cfg, self.host = name, rig, cfg, host
        self.faults = FaultPlan()
        self.simulators: list[StreamingADCSimulator] = []

    def start(self) -> list:
        from velab.errors import ConfigError
        from velab.simulators.bench import Endpoint

        eps = []
        for ep in self.cfg.get("endpoints") or [{"transport": "socket", "port": 0}]:
            tr = ep.get("transport", "socket")
            sim = StreamingADCSimulator(
                self.rig.analog_inputs, realtime=bool(self.cfg.get("realtime", True)),
                baud=self.cfg.get("baudrate"), faults=self.faults, clock=self.rig.clock,
                serial_no=str(self.cfg.get("serial_no", "SIM0001")),
            )
            if tr in ("socket", "tcp"):
                url = sim.serve_tcp(self.host, int(ep.get("port", 0) or 0))
                eps.append(Endpoint(self.name, "streaming_adc", "socket", url, port=int(url.rsplit(":", 1)[1])))
            elif tr == "pty":
                link = sim.serve_pty(ep.get("link") or None)
                eps.append(Endpoint(self.name, "streaming_adc", "pty", sim.slave_name, link=link))
            else:
                sim.close()
                raise ConfigError(f"[devices.{self.name}] endpoints: unknown transport {tr!r} (socket, pty)")
            self.simulators.append(sim)
        return eps

    def stop(self) -> None:
        for sim in self.simulators:
            sim.close()
        self.simulators = []


def _register() -> None:
    try:
        from velab.simulators.bench import register_sim_device
    except ImportError:  # the bench is optional
        return
    register_sim_device("streaming_adc", StreamingADCSimHandle)


_register()


def _fmt_rate(hz: float) -> str:
    return f"{hz:.3f}".rstrip("0").rstrip(".")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m velab.simulators.streaming_adc", description=__doc__.split("\n")[0])
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--tcp", type=int, metavar="PORT", help="listen on 127.0.0.1:PORT (0 = ephemeral)")
    g.add_argument("--pty", action="store_true", help="serve on a pty (prints the symlink to open)")
    ap.add_argument("--fast", action="store_true", help="stream as fast as the reader consumes")
    ap.add_argument("--baud", type=int, default=None, help="add wire time at this baud rate")
    args = ap.parse_args(argv)
    sim = StreamingADCSimulator(realtime=not args.fast, baud=args.baud)
    url = sim.serve_pty() if args.pty else sim.serve_tcp(port=args.tcp or 0)
    print(url, flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        sim.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
