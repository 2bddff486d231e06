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
consumes (at most ``fast_backlog_bytes`` ahead of it, and as much in a TCP link's
send buffer), the device clock still advancing by 1/fs per sample. ``baud`` adds the
wire time of 10 bits per byte. Fault injection through :class:`FaultPlan`; every
sample the simulator generated but did not deliver intact is counted in
``stats.samples_lost`` so tests can compare it with the driver's count.

Run standalone: ``python -m velab.simulators.streaming_adc --tcp 0 [--fast]``.
"""

from __future__ import annotations

import argparse
import errno
import os
import select
import socket
import tempfile
import threading
import time
import tty

from velab.drivers.sadc_protocol import ERR_LINE_TOO_LONG, MAX_LINE
from velab.errors import ConfigError
from velab.simulators.clock import buffer_scale
from velab.simulators.endpoint import Endpoint
from velab.simulators.sadc_device import (  # noqa: F401 - the device's names, re-exported
    FaultPlan,
    SADCDevice,
    SimStats,
    Source,
    default_source,
    ramp_source,
    sine_source,
)


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


class StreamingADCSimulator(SADCDevice):
    """The simulated device. ``serve_tcp()`` or ``serve_pty()``, then ``close()``."""

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
        schedule=None,
        name: str = "streaming_adc",
    ):
        super().__init__(source, faults=faults, serial_no=serial_no, firmware=firmware, clock=clock,
                         schedule=schedule, name=name)
        self.realtime = realtime
        self.baud = baud
        self.fifo_frames = fifo_frames
        self.fast_backlog_bytes = fast_backlog_bytes
        self.url: str | None = None
        self.pty_link: str | None = None
        self.slave_name: str | None = None
        self._closing = threading.Event()
        self._threads: list[threading.Thread] = []
        self._listener: socket.socket | None = None

    def fifo_bytes(self) -> int:
        """The FIFO's room for frames the host has not read. On a clock K x real time it holds K x
        ``fifo_frames``: the same *host* time as the device at real time (a test's speed-up must not
        turn a host's scheduling hiccup into an overrun the real device would never see; overruns are
        tested as faults, FaultPlan.overrun_at)."""
        return int(self.fifo_frames * buffer_scale(self.clock)) * self.frame_len

    def clock_scale(self) -> float:
        """Device seconds per host second: the simulation clock's scale (1 without one)."""
        return float(getattr(self.clock, "scale", 1.0) or 1.0) if self.clock is not None else 1.0

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
                        self._generate(min(due, 4096), out, self.fifo_bytes())
                    if self.clock is not None:
                        wait = ((self.frame_no + 1) * self.block / self.rate_hz
                                - (self.clock.now() - self._t_source0)) / self.clock_scale()
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
            if self._sched_disconnect and not out or (not self.running and self.disconnected_now()):
                self._sched_disconnect = False
                self.stats.disconnects += 1
                return "scheduled disconnect"
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
                            if not silent and not self.silent_now():
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
                    if reply is not None and not silent and not self.silent_now():
                        out += reply.encode("ascii") + b"\n"
            if w and out:
                n = len(out) if not self.baud else min(len(out), int(allowance))
                # a copy, not a memoryview of ``out``: a view kept alive a little longer (a caught socket error's
                # traceback holds send()'s frame; with the GUI's collector on a timer, until it runs) made the
                # ``del`` below raise BufferError and end the simulated device's session
                sent = link.send(out[: min(n, 65536)])  # (a bytearray slice is a copy)
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
            if self.disconnected_now():  # unplugged (scheduled): nobody answers
                conn.close()
                continue
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            if not self.realtime:
                # fast mode runs ``fast_backlog_bytes`` ahead of the host's reads, and the kernel's send buffer as
                # much again: left to itself it grows to megabytes on loopback (~1 MB of frames after STOP, 12 s of
                # the device's 10 kHz x 4 channels, that a loaded host parsed for over 5 s: "no reply to 'STOP'
                # within 5 s of frames"; ~0.2 MB with this bound)
                conn.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.fast_backlog_bytes)
            conn.setblocking(False)
            link = _Link(conn.fileno(), conn)
            why = self._session(link)
            link.close()
            self._reset_config()  # a power-cycled / re-plugged device comes back idle
            if why == "disconnect":
                self._unavailable(ls)
            elif why == "scheduled disconnect":
                self._unavailable(ls, scheduled=True)

    def _unavailable(self, ls: socket.socket, scheduled: bool = False) -> None:
        """Refuse connections for reconnect_delay_s, or while a scheduled disconnect lasts
        (for good if it has no end); clients queued meanwhile are dropped."""
        end = time.monotonic() + self.faults.reconnect_delay_s
        while (self.disconnected_now() if scheduled else time.monotonic() < end) and not self._closing.is_set():
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
            if why in ("disconnect", "scheduled disconnect"):
                os.unlink(self.pty_link)  # the device node vanishes ...
                link.close()
                os.close(self._slave)
                self._reset_config()
                if why == "disconnect":
                    self._closing.wait(self.faults.reconnect_delay_s)
                while self.disconnected_now() and not self._closing.wait(0.02):
                    pass  # unplugged for the scheduled window (for good: until cleared or closed)
                if self._closing.is_set():
                    self._master = self._slave = None
                    break
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


# ---------------------------------------------------------------- a SimulatedBench device (velab.simulators.bench)


class StreamingADCSimHandle:
    """The streaming ADC as a SimulatedBench device (``kind = "streaming_adc"``).

    Config keys: ``endpoints`` = list of ``{transport = "socket", port = N}`` /
    ``{transport = "pty", link = "/tmp/velab-sim/sadc"}``; ``realtime`` (default
    true); ``baudrate`` (adds wire time); ``serial_no``. The analogue inputs are
    the rig's ``analog_inputs`` on the rig's clock.
    """

    KEYS = {"kind", "endpoints", "realtime", "baudrate", "serial_no", "profile"}

    def __init__(self, name: str, rig, cfg: dict, host: str):
        unknown = sorted(set(cfg) - self.KEYS)
        if unknown:
            raise ConfigError(f"[devices.{name}] {unknown[0]}: unknown key (known: {', '.join(sorted(self.KEYS))})")
        self.name, self.rig, self.cfg, self.host = name, rig, cfg, host
        self.profile = cfg.get("profile")  # the driver's profile for the bench it serves (its inputs' calibrations)
        self.faults = FaultPlan()
        self.simulators: list[StreamingADCSimulator] = []

    def start(self) -> list:
        eps = []
        for ep in self.cfg.get("endpoints") or [{"transport": "socket", "port": 0}]:
            tr = ep.get("transport", "socket")
            sim = StreamingADCSimulator(
                self.rig.analog_inputs, realtime=bool(self.cfg.get("realtime", True)),
                baud=self.cfg.get("baudrate"), faults=self.faults, clock=self.rig.clock,
                serial_no=str(self.cfg.get("serial_no", "SIM0001")),
                schedule=getattr(self.rig, "schedule", None), name=self.name,
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

    def clear_faults(self) -> None:
        """Back to no frame-numbered faults (the FaultPlan is shared by every endpoint's simulator)."""
        for k, f in FaultPlan.__dataclass_fields__.items():
            setattr(self.faults, k, f.default_factory() if callable(f.default_factory) else f.default)


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
