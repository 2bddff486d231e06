"""Simulated DATAQ DI-series instrument served over a pty (as a USB CDC device appears) or TCP on 127.0.0.1.

The device is velab.simulators.dataq_device (the protocol, byte for byte); this module is its I/O:

* ``serve_pty(link)``: a pty whose slave is published as a stable symlink (``/tmp/.../dataq``), removed on an
  injected disconnect and re-pointed when the device comes back (a udev name for an unplugged USB device);
* ``serve_tcp(host, port)``: a listener for ``socket://127.0.0.1:PORT`` (port 0: ephemeral).

Scans are paced in real time at the configured rate (or on the simulation clock given) and sent in whole
packets of the ``ps`` size (a packet goes out only when full, p.21); ``stop`` flushes the last partial packet
and then echoes. A host that does not read lets the backlog grow: past the device's buffer (1024 samples, or
half a second of data if more: a loaded test host must not make an overflow the device would not) the
device reports ``stop 01`` and stops scanning (p.50).

Standalone: ``python -m velab.simulators.dataq_sim --pty /tmp/dataq --model DI-2108`` (or ``--tcp 0``).
"""

from __future__ import annotations

import argparse
import os
import select
import socket
import tempfile
import threading
import time
import tty
from dataclasses import dataclass

from velab.drivers import dataq_protocol as dq
from velab.errors import ConfigError
from velab.simulators.dataq_device import DataqDevice, DataqFaults
from velab.simulators.endpoint import Endpoint
from velab.simulators.streaming_adc import _Link

BUFFER_SAMPLES = 1024  # the instrument's buffer (p.50)


class DataqSimulator(DataqDevice):
    """The simulated instrument on a link. ``serve_pty()`` or ``serve_tcp()``, then ``close()``."""

    def __init__(self, model: str = "DI-2108", source=None, **kw):
        super().__init__(model, source, **kw)
        self.url: str | None = None
        self.pty_link: str | None = None
        self.slave_name: str | None = None
        self._closing = threading.Event()
        self._threads: list[threading.Thread] = []
        self._listener: socket.socket | None = None
        self._own_dir = False

    def _backlog_limit(self) -> int:
        return int(max(BUFFER_SAMPLES * 2, 0.5 * self.rate_hz * self.scan_bytes * self.clock_scale()))

    # ------------------------------------------------------------ one connection

    def _session(self, link: _Link) -> str:
        """Serve one link until it closes ('closed'), a disconnect fault ('disconnect') or close()."""
        self.stats.connections += 1
        inbuf, out = bytearray(), bytearray()
        while not self._closing.is_set():
            timeout = 0.05
            if self.scanning:
                point = self.fault_point()
                if point == "overflow":
                    out += self.overflow()
                elif point == "disconnect":
                    self._disconnects_left -= 1
                    self.stats.disconnects += 1
                    return "disconnect"  # what is still unsent never reaches the host
                elif point is None and not self.silent_now():
                    due = self.due_scans()
                    if due:
                        out += self.generate(min(due, max(1, 65536 // self.scan_bytes)))
                    timeout = min(timeout, self.next_scan_wait_s())
                if self.scanning and len(out) > self._backlog_limit():
                    out += self.overflow()  # the host stopped reading: the buffer overflowed
            if self.disconnected_now():
                self.stats.disconnects += 1
                return "scheduled disconnect"
            # while scanning only whole packets go out (p.21); otherwise (replies, the final flush) all of it
            sendable = len(out) - (len(out) % self.packet_size if self.scanning else 0)
            try:
                r, w, _ = select.select([link.fd], [link.fd] if sendable else [], [], timeout)
            except (OSError, ValueError):
                return "closed"
            if r:
                data = link.recv()
                if data is None:
                    return "closed"
                inbuf += data
                while True:
                    cr = inbuf.find(dq.CR)
                    if cr < 0:
                        if len(inbuf) > 256:  # no command is that long: a line noise burst
                            inbuf.clear()
                        break
                    line = bytes(inbuf[:cr])
                    del inbuf[:cr + 1]
                    reply = self.handle_line(line)
                    if reply is not None and not self.silent_now():
                        out += reply
                sendable = len(out) - (len(out) % self.packet_size if self.scanning else 0)
            if w and sendable:
                sent = link.send(out[:min(sendable, 65536)])  # (a bytearray slice is a copy)
                if sent < 0:
                    return "closed"
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
            if self.disconnected_now():
                conn.close()
                continue
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn.setblocking(False)
            link = _Link(conn.fileno(), conn)
            why = self._session(link)
            link.close()
            self.reset()  # a re-plugged device comes back idle
            if why != "closed":
                end = time.monotonic() + self.faults.reconnect_delay_s
                while ((self.disconnected_now() if why == "scheduled disconnect" else time.monotonic() < end)
                       and not self._closing.is_set()):
                    try:
                        ls.accept()[0].close()  # refused meanwhile
                    except socket.timeout:
                        pass
                    except OSError:
                        return

    # ------------------------------------------------------------ pty

    def serve_pty(self, link_path: str | None = None) -> str:
        """Create a pty; returns a stable symlink to its slave (what the driver, or any program, opens)."""
        self._own_dir = link_path is None
        if link_path is None:
            link_path = os.path.join(tempfile.mkdtemp(prefix="velab-dataq-"), "dataq")
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
            if why == "closed":
                time.sleep(0.01)
                continue
            os.unlink(self.pty_link)  # the device node vanishes ...
            link.close()
            os.close(self._slave)
            self.reset()
            if why == "disconnect":
                self._closing.wait(self.faults.reconnect_delay_s)
            while self.disconnected_now() and not self._closing.wait(0.02):
                pass
            if self._closing.is_set():
                self._master = self._slave = None
                break
            self._master, self._slave = self._new_pty()  # ... and comes back

    # ------------------------------------------------------------ lifecycle

    def _spawn(self, target) -> None:
        t = threading.Thread(target=target, name=f"dataq-sim {self.spec.name}", daemon=True)
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

    def __enter__(self) -> "DataqSimulator":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ---------------------------------------------------------------- a SimulatedBench device (velab.simulators.bench)


@dataclass(frozen=True)
class DataqEndpoint(Endpoint):
    """A DATAQ endpoint: the bench reaches it with one ``url`` (the pty's link, or socket://)."""

    def bench_settings(self) -> dict:
        return {"url": self.address if self.transport == "socket" else (self.link or self.address)}


class DataqSimHandle:
    """A DATAQ instrument as a SimulatedBench device (``kind = "dataq"``; the integrator registers it).

    Config keys: ``model`` (default "DI-2108"); ``endpoints`` = list of ``{transport = "socket", port = N}`` /
    ``{transport = "pty", link = "/tmp/velab-sim/dataq"}``; ``shunt_ohm`` = per input (default [250, 250]:
    the rig's 4-20 mA inputs 0 and 1 as 1..5 V); ``serial_no``; ``firmware``; ``digital_inputs`` (levels on
    the input ports); ``profile`` (the driver profile of the bench it serves). The analogue inputs are the
    rig's ``analog_inputs`` on the rig's clock; ``on_digital`` (set it before or after start) receives every
    output change as (line, level, t)."""

    KEYS = {"kind", "endpoints", "model", "shunt_ohm", "serial_no", "firmware", "digital_inputs", "profile"}

    def __init__(self, name: str, rig, cfg: dict, host: str):
        unknown = sorted(set(cfg) - self.KEYS)
        if unknown:
            raise ConfigError(f"[devices.{name}] {unknown[0]}: unknown key (known: {', '.join(sorted(self.KEYS))})")
        try:
            dq.model(cfg.get("model", "DI-2108"))
        except ValueError as exc:
            raise ConfigError(f"[devices.{name}] model: {exc}") from None
        self.name, self.rig, self.cfg, self.host = name, rig, cfg, host
        self.profile = cfg.get("profile")
        self.faults = DataqFaults()
        self.on_digital = None
        self.simulators: list[DataqSimulator] = []

    def _digital(self, line: int, level: bool, t: float) -> None:
        if self.on_digital is not None:
            self.on_digital(line, level, t)

    def start(self) -> list:
        eps = []
        for ep in self.cfg.get("endpoints") or [{"transport": "socket", "port": 0}]:
            tr = ep.get("transport", "socket")
            sim = DataqSimulator(
                self.cfg.get("model", "DI-2108"), self.rig.analog_inputs, shunt_ohm=self.cfg.get("shunt_ohm", (250.0, 250.0)),
                serial_no=str(self.cfg.get("serial_no", "5A1B2C3D")), firmware=str(self.cfg.get("firmware", "1.21")),
                on_digital=self._digital, faults=self.faults, clock=self.rig.clock,
                schedule=getattr(self.rig, "schedule", None), name=self.name,
                digital_inputs=int(self.cfg.get("digital_inputs", 0)),
            )
            if tr in ("socket", "tcp"):
                url = sim.serve_tcp(self.host, int(ep.get("port", 0) or 0))
                eps.append(DataqEndpoint(self.name, "dataq", "socket", url, port=int(url.rsplit(":", 1)[1])))
            elif tr == "pty":
                link = sim.serve_pty(ep.get("link") or None)
                eps.append(DataqEndpoint(self.name, "dataq", "pty", sim.slave_name, link=link))
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
        self.faults.clear()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m velab.simulators.dataq_sim", description=__doc__.split("\n")[0])
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--pty", metavar="LINK", help="serve on a pty, published as this symlink")
    g.add_argument("--tcp", type=int, metavar="PORT", help="listen on 127.0.0.1:PORT (0 = ephemeral)")
    ap.add_argument("--model", default="DI-2108", help=f"one of {', '.join(dq.MODELS)} (default DI-2108)")
    ap.add_argument("--serial", default="5A1B2C3D", help="what 'info 6' answers")
    ap.add_argument("--shunt", type=float, default=250.0, help="shunt (ohm) of inputs 0 and 1 (default 250)")
    args = ap.parse_args(argv)
    try:
        dq.model(args.model)
    except ValueError as exc:
        ap.error(str(exc))
    sim = DataqSimulator(args.model, serial_no=args.serial, shunt_ohm=(args.shunt, args.shunt))
    try:
        url = sim.serve_pty(args.pty) if args.pty else sim.serve_tcp(port=args.tcp or 0)
    except OSError as exc:
        ap.error(f"cannot serve: {exc}")
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
