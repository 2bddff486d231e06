"""SADC-4 streaming ADC: the serial link and its command/reply protocol (no streaming).

The transport is a pyserial URL or path (opened with serial_for_url) or an open
serial-like object. Every failure is a named DeviceError: DeviceDisconnected
(open / read / write failed), DeviceTimeout (no reply within command_s; a write
that blocks), DeviceException (an ``ERR <code>`` reply), ProtocolError (a reply
that is neither OK nor ERR).
"""

from __future__ import annotations

import functools
import re
import struct
import time
from pathlib import Path
from typing import Any

from velab.drivers.base import DeviceDisconnected, DeviceError, DeviceException, DeviceTimeout, ProtocolError
from velab.drivers.sadc_profile import StreamingADCProfile, default_profile
from velab.drivers.sadc_protocol import _STOP_REPLY, ERR_BUSY, ERROR_NAMES, MAX_LINE

_ERR_REPLY = re.compile(r"ERR (\d+)(?: (.*))?$")


def names_device(fn):
    """Errors escaping a public method carry the driver's name as their device."""

    @functools.wraps(fn)
    def wrapper(self, *args, **kw):
        try:
            return fn(self, *args, **kw)
        except DeviceError as exc:
            if exc.device is None:
                exc.device = self.name
            raise

    return wrapper


class SADCLink:
    """The command side of the SADC-4: open/close, ``command(line)``, ``identify()``."""

    def __init__(self, transport: Any = None, profile: StreamingADCProfile | None = None, *,
                 name: str = "streaming ADC"):
        self.profile = profile or default_profile()
        transport = transport if transport is not None else self.profile.url
        if transport is None:
            raise ValueError("StreamingADC needs a transport URL/path, a serial-like object, or a profile with device.url")
        self._url = transport if isinstance(transport, (str, Path)) else None
        self._port = None if self._url is not None else transport
        self.name = name
        self._rx = bytearray()  # bytes read past a reply line, handed to the stream parser
        self._streaming = False

    # ---------------------------------------------------------------- transport

    @names_device
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
            self._port = serial.serial_for_url(
                str(self._url), baudrate=self.profile.baudrate, timeout=self.profile.poll_s,
                write_timeout=self.profile.command_timeout_s,
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceDisconnected(f"{self.name}: cannot open {self._url}: {exc}") from exc

    def close(self) -> None:
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

    def __enter__(self) -> "SADCLink":
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _write(self, data: bytes) -> None:
        if self._port is None:
            raise DeviceDisconnected(f"{self.name}: port is not open")
        try:
            self._port.write(data)
        except Exception as exc:  # SerialException, SerialTimeoutException, OSError
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

    def _received(self) -> int:
        """Bytes received for this port and not read yet: the OS's count (FIONREAD, for a tty and a socket alike:
        pyserial's socket ``in_waiting`` says only whether there are any), else ``in_waiting``; 0 if neither says."""
        port = self._port
        try:
            import fcntl
            import termios

            return max(0, struct.unpack("i", fcntl.ioctl(port.fileno(), termios.FIONREAD, b"\0" * 4))[0])
        except Exception:  # no fileno (a test's fake), no fcntl (Windows)
            try:
                return max(0, int(port.in_waiting))
            except Exception:
                return 0

    # ---------------------------------------------------------------- commands

    @names_device
    def command(self, line: str) -> str:
        """Send one command line; return the reply text after ``OK`` (maybe empty).

        ``ERR <code> <text>`` raises DeviceException(code); no reply within
        ``command_timeout_s`` raises DeviceTimeout; a reply that is neither OK
        nor ERR raises ProtocolError. Not allowed while streaming.
        """
        if self._streaming:
            raise DeviceException(f"{self.name}: {line!r} refused: streaming (stop first)", ERR_BUSY)
        if self._port is None:
            self.open()
        self._write(line.encode("ascii") + b"\n")
        reply = self._read_line(line)
        return self._check_reply(line, reply)

    def _check_reply(self, line: str, reply: str) -> str:
        if reply == "OK" or reply.startswith("OK "):
            return reply[3:]
        m = _ERR_REPLY.match(reply)
        if m:
            code = int(m.group(1))
            raise DeviceException(f"{self.name}: {line!r} -> error {code} {m.group(2) or ERROR_NAMES.get(code, '')}".rstrip(), code)
        raise ProtocolError(f"{self.name}: {line!r} -> unexpected reply {reply!r}")

    def _read_line(self, what: str) -> str:
        deadline = time.monotonic() + self.profile.command_timeout_s
        while True:
            nl = self._rx.find(b"\n")
            if nl >= 0:
                raw = bytes(self._rx[:nl]).rstrip(b"\r")
                del self._rx[: nl + 1]
                try:
                    return raw.decode("ascii")
                except UnicodeDecodeError:
                    raise ProtocolError(f"{self.name}: {what!r} -> non-ASCII reply {raw!r}") from None
            if len(self._rx) > 4 * MAX_LINE:
                raise ProtocolError(f"{self.name}: {what!r} -> no line terminator in {bytes(self._rx[:32])!r}...")
            if time.monotonic() > deadline:
                more = self._read(0)  # what is waiting already (this thread may have been kept from running)
                if more:
                    self._rx += more
                    continue
                got = f" (got {bytes(self._rx)!r})" if self._rx else ""
                raise DeviceTimeout(f"{self.name}: no reply to {what!r} within {self.profile.command_timeout_s:g} s{got}")
            self._rx += self._read(1)

    def _stop_idle(self) -> int:
        """Send STOP outside streaming and skip anything (old frames) until its reply.

        The device may still be draining a backlog of frames: the wait restarts while
        bytes keep coming, up to 5 x command_s in all."""
        self._write(b"STOP\n")
        t_cmd = self.profile.command_timeout_s
        hard = time.monotonic() + 5 * t_cmd
        deadline = time.monotonic() + t_cmd
        final = False
        while True:
            m = _STOP_REPLY.search(self._rx)
            if m:
                total = int(m.group(1))
                del self._rx[: m.end()]
                return total
            e = re.search(rb"ERR (\d+)[^\n]*\n", self._rx)
            if e:
                line = bytes(e.group(0)).decode("ascii", "replace").strip()
                del self._rx[: e.end()]
                self._check_reply("STOP", line)
            if final:
                raise DeviceTimeout(f"{self.name}: no reply to 'STOP' within {self.profile.command_timeout_s:g} s")
            # once the time is up, what is waiting already is still read (this thread may have been kept from
            # running): that look is the last unless it brought bytes before the hard bound
            expired = time.monotonic() > min(deadline, hard)
            got = self._read(0 if expired else 64)
            if got:
                deadline = time.monotonic() + t_cmd
            final = expired and (not got or time.monotonic() > hard)
            self._rx += got
            if len(self._rx) > 1 << 20:
                del self._rx[: -MAX_LINE]

    @names_device
    def identify(self) -> str:
        return self.command("*IDN?")
