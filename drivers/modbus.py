"""velab's small Modbus client layer: the only driver module that imports pymodbus.

pymodbus (pinned 3.16.1) supplies the PDU codec (request encoding, reply
decoding) and the Modbus CRC; velab supplies the transaction engine on top of an
injected byte transport, so that timeouts, retries and reconnection are explicit,
every failure becomes a typed :mod:`velab.drivers.base` error, and tests can feed
exact bytes (see :class:`ExpectedProtocolTransport` in ``velab.drivers.testing``).

Layers::

    RegisterBus (Protocol)            read_holding / read_input / write_registers
      ModbusClient(transport, framing="tcp"|"rtu", unit, timeout_s, retries, reconnect)
        ByteTransport (Protocol)      open / close / write / read(n, deadline)
          TcpTransport(host, port)            Modbus TCP (MBAP framing)
          SerialTransport(url, baudrate...)   RTU on a port path, a pty, socket://host:port

Data types and word orders (``decode_registers`` / ``encode_value``): uint16, int16,
uint32, int32, float32, float64 in ABCD (big endian), CDAB (word swapped), BADC
(byte swapped) and DCBA (little endian).
"""

from __future__ import annotations

import enum
import socket
import struct
import threading
import time
from dataclasses import dataclass, field
from typing import Protocol, Sequence, runtime_checkable

from pymodbus.framer import FramerRTU
from pymodbus.pdu.decoders import DecodePDU
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersRequest,
    ReadInputRegistersRequest,
    WriteMultipleRegistersRequest,
)

from velab.drivers.base import (
    DeviceDisconnected,
    DeviceError,
    DeviceException,
    DeviceTimeout,
    ProtocolError,
)

MAX_READ_REGISTERS = 125
MAX_WRITE_REGISTERS = 123

EXCEPTION_NAMES = {
    1: "illegal function",
    2: "illegal data address",
    3: "illegal data value",
    4: "server device failure",
    5: "acknowledge",
    6: "server device busy",
    8: "memory parity error",
    10: "gateway path unavailable",
    11: "gateway target device failed to respond",
}


# ------------------------------------------------------------------ data types


class WordOrder(str, enum.Enum):
    """Order of the bytes of a multi-register value, A = most significant byte."""

    ABCD = "ABCD"  # big endian (Modbus default; pymodbus word_order="big")
    CDAB = "CDAB"  # low word first, bytes big endian inside a word (E+H "1-0-3-2")
    BADC = "BADC"  # high word first, bytes swapped inside each word
    DCBA = "DCBA"  # little endian

    @property
    def word_swap(self) -> bool:
        return self in (WordOrder.CDAB, WordOrder.DCBA)

    @property
    def byte_swap(self) -> bool:
        return self in (WordOrder.BADC, WordOrder.DCBA)


_TYPES = {  # name -> (struct code, registers)
    "uint16": ("H", 1),
    "int16": ("h", 1),
    "uint32": ("I", 2),
    "int32": ("i", 2),
    "float32": ("f", 2),
    "uint64": ("Q", 4),
    "float64": ("d", 4),
}
DATA_TYPES = tuple(_TYPES)


def register_count(dtype: str) -> int:
    try:
        return _TYPES[dtype][1]
    except KeyError:
        raise ValueError(f"unknown data type {dtype!r} (known: {', '.join(_TYPES)})") from None


def _reorder(words: list[int], order: WordOrder) -> list[int]:
    if order.byte_swap:
        words = [((w & 0xFF) << 8) | (w >> 8) for w in words]
    if order.word_swap:
        words = words[::-1]
    return words


def decode_registers(regs: Sequence[int], dtype: str, order: WordOrder | str = WordOrder.ABCD) -> int | float:
    """Registers (as on the wire, first address first) -> Python value."""
    code, n = _TYPES[dtype] if dtype in _TYPES else (None, register_count(dtype))
    if len(regs) != n:
        raise ValueError(f"{dtype} needs {n} registers, got {len(regs)}")
    words = _reorder(list(regs), WordOrder(order))  # the transform is its own inverse
    return struct.unpack(">" + code, struct.pack(f">{n}H", *words))[0]


def encode_value(value: int | float, dtype: str, order: WordOrder | str = WordOrder.ABCD) -> list[int]:
    """Python value -> registers in wire order."""
    code, n = _TYPES[dtype] if dtype in _TYPES else (None, register_count(dtype))
    if code in "HhIiQ":
        value = int(value)
    try:
        words = list(struct.unpack(f">{n}H", struct.pack(">" + code, value)))
    except struct.error as exc:
        raise ValueError(f"{value!r} does not fit a {dtype}: {exc}") from None
    return _reorder(words, WordOrder(order))


def crc16(data: bytes) -> bytes:
    """Modbus CRC-16 as it goes on the wire (low byte first)."""
    return FramerRTU.compute_CRC(data).to_bytes(2, "big")


# ------------------------------------------------------------------ transports


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
    def discard_input(self) -> None: ...


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
            self._sock.sendall(data)
        except OSError as exc:
            self.close()
            raise DeviceDisconnected(f"{self.name}: connection lost while sending: {exc}") from exc

    def read(self, n: int, deadline: float) -> bytes:
        if self._sock is None:
            raise DeviceDisconnected(f"{self.name}: not connected")
        buf = bytearray()
        while len(buf) < n:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            self._sock.settimeout(remaining)
            try:
                chunk = self._sock.recv(n - len(buf))
            except socket.timeout:
                break
            except OSError as exc:
                self.close()
                raise DeviceDisconnected(f"{self.name}: connection lost: {exc}") from exc
            if not chunk:
                self.close()
                raise DeviceDisconnected(f"{self.name}: connection closed by the device")
            buf += chunk
        return bytes(buf)

    def discard_input(self) -> None:
        if self._sock is None:
            return
        self._sock.setblocking(False)
        try:
            while self._sock.recv(4096):
                pass
        except (BlockingIOError, OSError):
            pass
        finally:
            if self._sock is not None:
                self._sock.setblocking(True)


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
            if remaining <= 0:
                break
            self._ser.timeout = remaining
            try:
                chunk = self._ser.read(n - len(buf))
            except (serial.SerialException, OSError) as exc:
                self.close()
                raise DeviceDisconnected(f"{self.name}: read failed: {exc}") from exc
            buf += chunk
        return bytes(buf)

    def discard_input(self) -> None:
        if self._ser is not None:
            try:
                self._ser.reset_input_buffer()
            except Exception:  # noqa: BLE001
                pass


# ------------------------------------------------------------------ the bus


@runtime_checkable
class RegisterBus(Protocol):
    """What a Modbus driver needs: register reads and writes to one unit id."""

    unit: int

    def read_holding(self, address: int, count: int, unit: int | None = None) -> list[int]: ...
    def read_input(self, address: int, count: int, unit: int | None = None) -> list[int]: ...
    def write_registers(self, address: int, values: Sequence[int], unit: int | None = None) -> None: ...
    def close(self) -> None: ...


@dataclass
class BusStats:
    requests: int = 0
    retries: int = 0
    timeouts: int = 0
    protocol_errors: int = 0
    exceptions: int = 0
    reconnects: int = 0


class ModbusClient:
    """Synchronous Modbus master over a ByteTransport (TCP or RTU framing).

    timeout_s : per attempt, from sending the request to the last reply byte.
    retries : further attempts after a timeout, a garbled reply or a lost connection
        (a Modbus exception reply is an answer and is never retried).
    reconnect : re-open a lost transport before the next attempt.
    """

    def __init__(self, transport: ByteTransport, framing: str = "tcp", *, unit: int = 1,
                 timeout_s: float = 0.5, retries: int = 2, reconnect: bool = True,
                 name: str | None = None, turnaround_s: float = 0.0):
        if framing not in ("tcp", "rtu"):
            raise ValueError(f"framing must be 'tcp' or 'rtu', got {framing!r}")
        if timeout_s <= 0:
            raise ValueError("timeout_s must be positive")
        if retries < 0:
            raise ValueError("retries must be >= 0")
        self.transport = transport
        self.framing = framing
        self.unit = unit
        self.timeout_s = timeout_s
        self.retries = retries
        self.reconnect = reconnect
        self.turnaround_s = turnaround_s
        self.name = name or transport.name
        self.stats = BusStats()
        self._tid = 0
        self._was_open = False
        self._lock = threading.RLock()
        self._decoder = DecodePDU(is_server=False)

    # -- context
    def connect(self) -> "ModbusClient":
        with self._lock:
            self.transport.open()
            self._was_open = True
        return self

    def close(self) -> None:
        with self._lock:
            self.transport.close()

    def __enter__(self) -> "ModbusClient":
        return self.connect()

    def __exit__(self, *exc) -> None:
        self.close()

    # -- public register access
    def read_holding(self, address: int, count: int, unit: int | None = None) -> list[int]:
        self._check_range(address, count, MAX_READ_REGISTERS)
        req = ReadHoldingRegistersRequest(address=address, count=count)
        return self._transact(req, unit, f"read holding {address}+{count}").registers[:count]

    def read_input(self, address: int, count: int, unit: int | None = None) -> list[int]:
        self._check_range(address, count, MAX_READ_REGISTERS)
        req = ReadInputRegistersRequest(address=address, count=count)
        return self._transact(req, unit, f"read input {address}+{count}").registers[:count]

    def write_registers(self, address: int, values: Sequence[int], unit: int | None = None) -> None:
        values = [int(v) for v in values]
        self._check_range(address, len(values), MAX_WRITE_REGISTERS)
        if any(not 0 <= v <= 0xFFFF for v in values):
            raise ValueError(f"register values must be 0..65535, got {values}")
        req = WriteMultipleRegistersRequest(address=address, registers=values)
        reply = self._transact(req, unit, f"write {address}+{len(values)}")
        if reply.address != address or reply.count != len(values):
            raise ProtocolError(
                f"{self.name}: write {address}+{len(values)} acknowledged as {reply.address}+{reply.count}"
            )

    @staticmethod
    def _check_range(address: int, count: int, limit: int) -> None:
        if not 0 <= address <= 0xFFFF:
            raise ValueError(f"address must be 0..65535, got {address}")
        if not 1 <= count <= limit:
            raise ValueError(f"count must be 1..{limit}, got {count}")
        if address + count > 0x10000:
            raise ValueError(f"address {address} + count {count} runs past 65535")

    # -- the transaction engine
    def _frame(self, pdu: bytes, unit: int) -> tuple[bytes, int]:
        if self.framing == "rtu":
            adu = bytes([unit]) + pdu
            return adu + crc16(adu), 0
        self._tid = (self._tid + 1) & 0xFFFF
        return struct.pack(">HHHB", self._tid, 0, len(pdu) + 1, unit) + pdu, self._tid

    def _transact(self, req, unit: int | None, what: str):
        unit = self.unit if unit is None else unit
        pdu = bytes([req.function_code]) + req.encode()
        last: DeviceError | None = None
        with self._lock:
            for attempt in range(self.retries + 1):
                if attempt:
                    self.stats.retries += 1
                try:
                    if not self.transport.is_open:
                        if self._was_open:
                            if not self.reconnect:
                                raise DeviceDisconnected(f"{self.name}: connection lost (reconnect disabled)")
                            self.stats.reconnects += 1
                        self.transport.open()
                        self._was_open = True
                    frame, tid = self._frame(pdu, unit)
                    self.stats.requests += 1
                    if self.turnaround_s:
                        time.sleep(self.turnaround_s)
                    self.transport.write(frame)
                    reply_pdu = self._receive(req.function_code, unit, tid, what)
                    return self._decode(reply_pdu, req.function_code, unit, what)
                except DeviceException:
                    raise
                except DeviceTimeout as exc:
                    self.stats.timeouts += 1
                    last = exc
                except ProtocolError as exc:
                    self.stats.protocol_errors += 1
                    last = exc
                    self._resync()
                except DeviceDisconnected as exc:
                    last = exc
                    self.transport.close()
                    if not self.reconnect:
                        raise
                    time.sleep(min(0.05, self.timeout_s))
        assert last is not None
        if self.retries:
            msg = f"{last} (after {self.retries + 1} attempts)"
            raise type(last)(msg) from last
        raise last

    def _resync(self) -> None:
        """After a garbled reply: let the line go quiet, then drop what arrived."""
        if self.framing == "rtu":
            time.sleep(0.005)
        self.transport.discard_input()

    def _read_exact(self, n: int, deadline: float, what: str, got: bytes = b"") -> bytes:
        data = self.transport.read(n, deadline)
        if len(data) < n:
            if not data and not got:
                raise DeviceTimeout(f"{self.name} unit {self.unit}: no reply to {what} within {self.timeout_s:g} s")
            raise ProtocolError(
                f"{self.name}: truncated reply to {what}: got {len(got) + len(data)} bytes, "
                f"expected {len(got) + n} ({(got + data).hex(' ')})"
            )
        return data

    def _receive(self, fc: int, unit: int, tid: int, what: str) -> bytes:
        deadline = time.monotonic() + self.timeout_s
        if self.framing == "tcp":
            while True:
                head = self._read_exact(7, deadline, what)
                rtid, proto, length, runit = struct.unpack(">HHHB", head)
                if proto != 0 or not 2 <= length <= 254:
                    raise ProtocolError(f"{self.name}: bad MBAP header {head.hex(' ')} in reply to {what}")
                body = self._read_exact(length - 1, deadline, what, head)
                if rtid != tid:  # a late reply to an earlier, timed-out request: skip it
                    continue
                if runit != unit:
                    raise ProtocolError(f"{self.name}: reply to {what} from unit {runit}, expected {unit}")
                return body
        # RTU: address, function, then either an exception code or a byte count
        head = self._read_exact(3, deadline, what)
        raddr, rfc, third = head
        if rfc == fc | 0x80:
            n_rest = 2
        elif rfc != fc:
            raise ProtocolError(f"{self.name}: reply to {what} has function code {rfc}, expected {fc} ({head.hex(' ')})")
        elif fc in (3, 4):
            n_rest = third + 2
        else:  # 16: address(2) count(2) crc(2), third is the first address byte
            n_rest = 5
        rest = self._read_exact(n_rest, deadline, what, head)
        frame = head + rest
        if crc16(frame[:-2]) != frame[-2:]:
            raise ProtocolError(f"{self.name}: CRC error in reply to {what} ({frame.hex(' ')})")
        if raddr != unit:
            raise ProtocolError(f"{self.name}: reply to {what} from unit {raddr}, expected {unit}")
        return frame[1:-2]

    def _decode(self, body: bytes, fc: int, unit: int, what: str):
        if body and body[0] == fc | 0x80:
            code = body[1] if len(body) > 1 else None
            self.stats.exceptions += 1
            name = EXCEPTION_NAMES.get(code, "unknown exception")
            raise DeviceException(f"{self.name} unit {unit}: {what} refused: Modbus exception {code} ({name})", code)
        if not body or body[0] != fc:
            raise ProtocolError(f"{self.name}: reply to {what} has function code {body[:1].hex()}, expected {fc:02x}")
        if fc in (3, 4) and (len(body) < 2 or body[1] != len(body) - 2 or body[1] % 2):
            raise ProtocolError(f"{self.name}: reply to {what} has inconsistent byte count ({body.hex(' ')})")
        if fc == 16 and len(body) != 5:
            raise ProtocolError(f"{self.name}: reply to {what} has wrong length ({body.hex(' ')})")
        reply = self._decoder.decode(body)
        if reply is None:
            raise ProtocolError(f"{self.name}: undecodable reply to {what} ({body.hex(' ')})")
        return reply


# ------------------------------------------------------------------ endpoints


@dataclass(frozen=True)
class BusSettings:
    """How to reach a Modbus device: the ``[devices.X]`` table of a bench config.

    transport = "tcp": host, port. transport = "rtu": port = a serial device path,
    a pty path or ``socket://host:port``; baudrate, parity, stopbits, bytesize.
    """

    transport: str = "tcp"
    host: str = "127.0.0.1"
    port: int | str = 502
    unit: int = 1
    timeout_s: float = 0.5
    retries: int = 2
    reconnect: bool = True
    baudrate: int = 19200
    parity: str = "N"
    stopbits: float = 1
    bytesize: int = 8
    extra: dict = field(default_factory=dict)

    @classmethod
    def from_dict(cls, d: dict, where: str = "device") -> "BusSettings":
        from velab.drivers.base import ProfileError

        from velab.tomlschema import Reader, above, within

        r = Reader(None, d, error=ProfileError)
        w = f"{where} "
        known = {f for f in cls.__dataclass_fields__ if f != "extra"}
        extra = {k: v for k, v in d.items() if k not in known}
        transport = r.get(d, w, "transport", str, "tcp", choices=("tcp", "rtu"))
        if transport == "tcp":
            port = r.get(d, w, "port", int, 502, check=within(1, 65535))
        else:
            port = r.get(d, w, "port", str, check=lambda v: None if v.strip() else "must not be empty")
        s = cls(
            transport=transport, host=r.get(d, w, "host", str, "127.0.0.1"), port=port,
            unit=r.get(d, w, "unit", int, 1, check=within(0, 247)),
            timeout_s=r.get(d, w, "timeout_s", float, 0.5, check=above(0, 600, "s")),
            retries=r.get(d, w, "retries", int, 2, check=within(0, 100)),
            reconnect=r.get(d, w, "reconnect", bool, True),
            baudrate=r.get(d, w, "baudrate", int, 19200, check=within(50, 4_000_000)),
            parity=r.get(d, w, "parity", str, "N", choices=("N", "E", "O")),
            stopbits=r.get(d, w, "stopbits", float, 1, choices=(1.0, 1.5, 2.0)),
            bytesize=r.get(d, w, "bytesize", int, 8, choices=(5, 6, 7, 8)),
            extra=extra,
        )
        return s

    @property
    def endpoint(self) -> str:
        return f"tcp://{self.host}:{self.port}" if self.transport == "tcp" else f"rtu:{self.port}@{self.baudrate}"


def open_bus(settings: BusSettings | dict, *, connect: bool = True, name: str | None = None) -> ModbusClient:
    """Build (and by default connect) a ModbusClient from bench settings."""
    if isinstance(settings, dict):
        settings = BusSettings.from_dict(settings)
    if settings.transport == "tcp":
        transport: ByteTransport = TcpTransport(settings.host, int(settings.port), connect_timeout_s=settings.timeout_s)
        framing = "tcp"
    else:
        transport = SerialTransport(str(settings.port), settings.baudrate, settings.bytesize, settings.parity, settings.stopbits)
        framing = "rtu"
    client = ModbusClient(transport, framing, unit=settings.unit, timeout_s=settings.timeout_s,
                          retries=settings.retries, reconnect=settings.reconnect, name=name)
    if connect:
        client.connect()
    return client
