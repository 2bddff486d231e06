"""Byte transports for the Modbus client: TCP sockets and serial lines (pyserial URLs).

A transport moves bytes and turns OS failures into DeviceDisconnected; framing,
timeouts and checks are the client's (velab.drivers.modbus).
"""

from __future__ import annotations

import select
import socket
import time
from typing import Protocol, runtime_checkable

from velab.drivers.base import DeviceDisconnected


@runtime_checkable
class ByteTransport(Protocol):
    """A byte pipe. ``read`` returns at most n bytes, fewer (maybe none) at the deadline."""

    name: str

    def open(self) -> None: ...
    def close(self) -> None: ...
    @property
    def is_open(self) -> bool: ...
    def write(self, data: bytes) -> None: ...
    def read(self, n: int, deadline: float) -> bytes: ...
    def discard_input(self) -> int: ...  # bytes dropped (0 if unknown)


class TcpTransport:
    """A TCP connection (Modbus TCP). Failures become DeviceDisconnected."""

    def __init__(self, host: str, port: int, connect_timeout_s: float = 1.0):
        self.host, self.port = host, int(port)
        self.connect_timeout_s = connect_timeout_s
        self.name = f"tcp://{host}:{port}"
        self._sock: socket.socket | None = None

    @property
    def is_open(self) -> bool:
        return self._sock is not None

    def open(self) -> None:
        if self._sock is not None:
            return
        try:
            s = socket.create_connection((self.host, self.port), timeout=self.connect_timeout_s)
        except OSError as exc:
            raise DeviceDisconnected(f"{self.name}: cannot connect: {exc}") from exc
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock = s

    def close(self) -> None:
        if self._sock is not None:
            try:
                self._sock.close()
            finally:
                self._sock = None

    def write(self, data: bytes) -> None:
        if self._sock is None:
            raise DeviceDisconnected(f"{self.name}: not connected")
        try:
            self._sock.settimeout(self.connect_timeout_s)  # (a read may have left it non-blocking)
            self._sock.sendall(data)
        except OSError as exc:
            self.close()
            raise DeviceDisconnected(f"{self.name}: connection lost while sending: {exc}") from exc

    def read(self, n: int, deadline: float) -> bytes:
        if self._sock is None:
            raise DeviceDisconnected(f"{self.name}: not connected")
        buf = bytearray()
        while len(buf) < n:
            # past the deadline, what has already arrived is still taken (non-blocking): a reader that woke late
            # on a busy host has not met a silent device
            self._sock.settimeout(max(0.0, deadline - time.monotonic()))
            try:
                chunk = self._sock.recv(n - len(buf))
            except (socket.timeout, BlockingIOError):
                break
            except OSError as exc:
                self.close()
                raise DeviceDisconnected(f"{self.name}: connection lost: {exc}") from exc
            if not chunk:
                self.close()
                raise DeviceDisconnected(f"{self.name}: connection closed by the device")
            buf += chunk
        return bytes(buf)

    def pending(self) -> bool:
        """Bytes already received and not read (no waiting)."""
        if self._sock is None:
            return False
        try:
            if not select.select([self._sock], [], [], 0)[0]:
                return False
            return bool(self._sock.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT))  # b"": the peer closed
        except (OSError, ValueError):
            return False

    def discard_input(self) -> int:
        if self._sock is None:
            return 0
        n = 0
        self._sock.setblocking(False)
        try:
            while chunk := self._sock.recv(4096):
                n += len(chunk)
        except (BlockingIOError, OSError):
            pass
        finally:
            if self._sock is not None:
                self._sock.setblocking(True)
        return n


class SerialTransport:
    """A serial line through pyserial's ``serial_for_url``: a device path, a pty, ``socket://host:port``."""

    def __init__(self, url: str, baudrate: int = 19200, bytesize: int = 8, parity: str = "N", stopbits: float = 1):
        self.url, self.baudrate = url, baudrate
        self.bytesize, self.parity, self.stopbits = bytesize, parity, stopbits
        self.name = url
        self._ser = None

    @property
    def is_open(self) -> bool:
        return self._ser is not None

    @property
    def char_time_s(self) -> float:
        bits = 1 + self.bytesize + (0 if self.parity == "N" else 1) + self.stopbits
        return bits / self.baudrate

    def open(self) -> None:
        if self._ser is not None:
            return
        import serial

        try:
            self._ser = serial.serial_for_url(
                self.url, baudrate=self.baudrate, bytesize=self.bytesize, parity=self.parity,
                stopbits=self.stopbits, timeout=0.1, write_timeout=1.0,
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceDisconnected(f"{self.name}: cannot open: {exc}") from exc

    def close(self) -> None:
        if self._ser is not None:
            try:
                self._ser.close()
            except Exception:  # noqa: BLE001 - closing a dead port must not mask the real error
                pass
            self._ser = None

    def write(self, data: bytes) -> None:
        import serial

        if self._ser is None:
            raise DeviceDisconnected(f"{self.name}: not open")
        try:
            self._ser.write(data)
        except (serial.SerialException, OSError) as exc:
            self.close()
            raise DeviceDisconnected(f"{self.name}: write failed: {exc}") from exc

    def read(self, n: int, deadline: float) -> bytes:
        import serial

        if self._ser is None:
            raise DeviceDisconnected(f"{self.name}: not open")
        buf = bytearray()
        while len(buf) < n:
            remaining = deadline - time.monotonic()
            self._ser.timeout = max(0.0, remaining)  # past the deadline: what has arrived is still taken (as TCP)
            try:
                chunk = self._ser.read(n - len(buf))
            except (serial.SerialException, OSError) as exc:
                self.close()
                raise DeviceDisconnected(f"{self.name}: read failed: {exc}") from exc
            buf += chunk
            if remaining <= 0 and not chunk:
                break
        return bytes(buf)

    def discard_input(self) -> int:
        if self._ser is None:
            return 0
        try:
            n = self._ser.in_waiting
            self._ser.reset_input_buffer()
            return int(n)
        except Exception:  # noqa: BLE001 - a dead port shows at the next read or write
            return 0
