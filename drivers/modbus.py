"""velab's small Modbus client: the only driver module that imports pymodbus.

pymodbus (pinned 3.16.1) supplies the PDU codec (request encoding, reply
decoding) and the Modbus CRC; velab supplies the transaction engine on top of an
injected byte transport, so that timeouts, retries and reconnection are explicit,
every reply is checked before use, every failure is a named
:mod:`velab.drivers.base` error, and tests can feed exact bytes (see
``velab.drivers.testing.ExpectedProtocolTransport``).

Layers::

    RegisterBus (Protocol)            read_holding / read_input / write_registers
      ModbusClient(transport, framing="tcp"|"rtu", unit, timeout_s, retries, reconnect)
        ByteTransport (Protocol)      velab.drivers.modbus_transport: TcpTransport, SerialTransport
    data types / word orders          velab.drivers.modbus_types

Reply checks (any failure is a ProtocolError subclass naming the device and the
reason, the reply is never used, and the request is retried up to ``retries``):

* RTU: CRC (ChecksumError); unit id and function code (ReplyMismatch); frame
  length from the function code and byte count, short (truncated) or long
  (bytes trailing the frame within the inter-frame silence) (FrameError); byte
  count equal to 2 x the requested register count (FrameError "byte_count");
  write echo equal to the request's address and count.
* TCP: MBAP protocol id 0 and length 2..254 (FrameError "bad_header"); the MBAP
  length equal to the PDU's own length (FrameError short/long); transaction id:
  a recent earlier id is a late reply and is skipped, any other id is a
  ReplyMismatch "wrong_transaction"; unit id; function code; byte count.
* Exception replies (0x80 | fc) are DeviceException(code), never retried.
* Late replies: before each request the input is flushed; after an RTU timeout
  the client waits for the line to go quiet and drops what arrived, so a late
  reply is never taken as the answer to the next request (RTU has no
  transaction id).
"""

from __future__ import annotations

import struct
import threading
import time
from collections import deque
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
    ChecksumError,
    ProfileError,
    DeviceDisconnected,
    DeviceError,
    DeviceException,
    DeviceTimeout,
    FrameError,
    ProtocolError,
    ReplyMismatch,
)
from velab.drivers.modbus_transport import ByteTransport, SerialTransport, TcpTransport
from velab.drivers.modbus_types import DATA_TYPES, WordOrder, decode_registers, encode_value, register_count
from velab.tomlschema import Reader, above, within

__all__ = [
    "BusSettings", "BusStats", "ByteTransport", "DATA_TYPES", "MAX_READ_REGISTERS", "MAX_WRITE_REGISTERS",
    "ModbusClient", "RegisterBus", "SerialTransport", "TcpTransport", "WordOrder", "crc16", "decode_registers",
    "encode_value", "open_bus", "register_count",
]

MAX_READ_REGISTERS = 125
MAX_WRITE_REGISTERS = 123
MIN_FRAME_GAP_S = 0.00175  # Modbus RTU t3.5 floor (baud rates above 19200)
# after a failed exchange, once bytes have come: the silence that ends the wait for the line to go quiet. A slave
# answering the requests it queued while busy, or a USB adapter's latency timer (16 ms by default on FTDI),
# delivers a backlog in pieces further apart than t3.5; a quiet line declared between two of them left the next
# one to be read as the answer to the next request
QUIET_AFTER_BYTES_S = 0.1

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


def crc16(data: bytes) -> bytes:
    """Modbus CRC-16 as it goes on the wire (low byte first)."""
    return FramerRTU.compute_CRC(data).to_bytes(2, "big")


# ------------------------------------------------------------------ the bus


@runtime_checkable
class RegisterBus(Protocol):
    """What a Modbus driver needs: register reads and writes to one unit id."""

    unit: int
    timeout_s: float  # the longest a reply may take (a request whose reply was lost may still be executed within it)

    def read_holding(self, address: int, count: int, unit: int | None = None) -> list[int]: ...
    def read_input(self, address: int, count: int, unit: int | None = None) -> list[int]: ...
    def write_registers(self, address: int, values: Sequence[int], unit: int | None = None,
                        retries: int | None = None) -> None: ...
    def close(self) -> None: ...


@dataclass
class BusStats:
    requests: int = 0
    retries: int = 0
    timeouts: int = 0
    protocol_errors: int = 0
    exceptions: int = 0
    reconnects: int = 0
    late_replies: int = 0  # replies to earlier (timed-out) requests, recognised and dropped
    flushed_bytes: int = 0  # stray bytes dropped before a request or after a timeout


@dataclass(frozen=True)
class _Expect:
    """What the reply to one request must look like."""

    fc: int
    unit: int
    tid: int
    count: int = 0  # registers (reads)
    address: int = 0  # writes: the echo
    what: str = ""

    @property
    def pdu_len(self) -> int:  # PDU length of the normal reply: fc + byte count + data, or fc + addr + count
        return 2 + 2 * self.count if self.fc in (3, 4) else 5


class ModbusClient:
    """Synchronous Modbus master over a ByteTransport (TCP or RTU framing).

    timeout_s : per attempt, from sending the request to the last reply byte.
    retries : further attempts after a timeout, a rejected reply or a lost connection
        (a Modbus exception reply is an answer and is never retried). A call takes at
        most about (retries + 1) x 2 x timeout_s.
    reconnect : re-open a lost transport before the next attempt.
    frame_gap_s : RTU inter-frame silence (t3.5); default from the line's baud rate.
    """

    def __init__(self, transport: ByteTransport, framing: str = "tcp", *, unit: int = 1,
                 timeout_s: float = 0.5, retries: int = 2, reconnect: bool = True,
                 name: str | None = None, turnaround_s: float = 0.0, frame_gap_s: float | None = None):
        if framing not in ("tcp", "rtu"):
            raise ValueError(f"framing must be 'tcp' or 'rtu', got {framing!r}")
        if not timeout_s > 0:
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
        if frame_gap_s is None:
            frame_gap_s = max(MIN_FRAME_GAP_S, 3.5 * getattr(transport, "char_time_s", 0.0))
        self.frame_gap_s = frame_gap_s
        self.name = name or transport.name
        self.stats = BusStats()
        self._tid = 0
        self._recent_tids: deque[int] = deque(maxlen=16)
        self._was_open = False
        self._lock = threading.RLock()
        self._decoder = DecodePDU(is_server=False)

    # -- context
    def connect(self) -> "ModbusClient":
        with self._lock:
            try:
                self.transport.open()
            except DeviceDisconnected as exc:
                raise self._named(exc) from exc.__cause__
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
        return self._transact(req, unit, f"read holding {address}+{count}", count=count).registers[:count]

    def read_input(self, address: int, count: int, unit: int | None = None) -> list[int]:
        self._check_range(address, count, MAX_READ_REGISTERS)
        req = ReadInputRegistersRequest(address=address, count=count)
        return self._transact(req, unit, f"read input {address}+{count}", count=count).registers[:count]

    def write_registers(self, address: int, values: Sequence[int], unit: int | None = None,
                        retries: int | None = None) -> None:
        """FC16. ``retries`` overrides the client's (0 for commands that must not be repeated blindly)."""
        values = [int(v) for v in values]
        self._check_range(address, len(values), MAX_WRITE_REGISTERS)
        if any(not 0 <= v <= 0xFFFF for v in values):
            raise ValueError(f"register values must be 0..65535, got {values}")
        req = WriteMultipleRegistersRequest(address=address, registers=values)
        self._transact(req, unit, f"write {address}+{len(values)}", count=len(values), address=address,
                       retries=retries)

    @staticmethod
    def _check_range(address: int, count: int, limit: int) -> None:
        if not 0 <= address <= 0xFFFF:
            raise ValueError(f"address must be 0..65535, got {address}")
        if not 1 <= count <= limit:
            raise ValueError(f"count must be 1..{limit}, got {count}")
        if address + count > 0x10000:
            raise ValueError(f"address {address} + count {count} runs past 65535")

    # -- errors carry the device's name
    def _named(self, exc: DeviceError) -> DeviceError:
        if exc.device is None:
            exc.device = self.name
        return exc

    def _err(self, cls, reason: str, exp: _Expect, text: str, frame: bytes = b"") -> DeviceError:
        shown = f" ({frame.hex(' ')})" if frame else ""
        return cls(f"{self.name} unit {exp.unit}: {exp.what}: {text}{shown}", device=self.name, reason=reason)

    # -- the transaction engine
    def _frame(self, pdu: bytes, unit: int) -> tuple[bytes, int]:
        if self.framing == "rtu":
            adu = bytes([unit]) + pdu
            return adu + crc16(adu), 0
        self._tid = (self._tid + 1) & 0xFFFF
        self._recent_tids.append(self._tid)
        return struct.pack(">HHHB", self._tid, 0, len(pdu) + 1, unit) + pdu, self._tid

    def _transact(self, req, unit: int | None, what: str, *, count: int = 0, address: int = 0,
                  retries: int | None = None):
        unit = self.unit if unit is None else unit
        retries = self.retries if retries is None else retries
        pdu = bytes([req.function_code]) + req.encode()
        last: DeviceError | None = None
        with self._lock:
            for attempt in range(retries + 1):
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
                    self._flush("before " + what)
                    frame, tid = self._frame(pdu, unit)
                    exp = _Expect(req.function_code, unit, tid, count, address, what)
                    self.stats.requests += 1
                    if self.turnaround_s:
                        time.sleep(self.turnaround_s)
                    self.transport.write(frame)
                    body = self._receive(exp)
                    return self._decode(body, exp)
                except DeviceException as exc:
                    raise self._named(exc)
                except DeviceTimeout as exc:
                    self.stats.timeouts += 1
                    last = exc
                    self._quiet_line()
                except ProtocolError as exc:
                    self.stats.protocol_errors += 1
                    last = exc
                    self._quiet_line(bytes_came=True)
                except DeviceDisconnected as exc:
                    last = exc
                    self.transport.close()
                    if not self.reconnect:
                        raise self._named(exc)
                    time.sleep(min(0.05, self.timeout_s))
        assert last is not None
        self._named(last)
        if retries:
            raise last.again(f"{last} (after {retries + 1} attempts)") from last
        raise last

    def _flush(self, when: str) -> None:
        """Drop stray bytes (a late reply to an earlier request) before sending."""
        dropped = self.transport.discard_input()
        if dropped:
            self.stats.flushed_bytes += int(dropped)

    def _quiet_line(self, bytes_came: bool = False) -> None:
        """After a timeout or a rejected reply (``bytes_came``): wait until nothing has arrived
        for one inter-frame gap, or for QUIET_AFTER_BYTES_S once something has (RTU; bounded by
        timeout_s), dropping what came, then flush."""
        if self.framing == "rtu" and self.transport.is_open:
            end = time.monotonic() + self.timeout_s
            gap = max(self.frame_gap_s, 0.005, QUIET_AFTER_BYTES_S if bytes_came else 0.0)
            while time.monotonic() < end:
                try:
                    got = self.transport.read(256, min(end, time.monotonic() + gap))
                except DeviceDisconnected:
                    return
                if not got:
                    break
                self.stats.flushed_bytes += len(got)
                gap = max(gap, QUIET_AFTER_BYTES_S)
        if self.transport.is_open:
            self._flush("after a failed exchange")

    def _pending(self) -> bool:
        pending = getattr(self.transport, "pending", None)
        return bool(pending()) if pending is not None else False

    def _read_exact(self, n: int, deadline: float, exp: _Expect, got: bytes = b"") -> bytes:
        data = self.transport.read(n, deadline)
        if len(data) < n:
            if not data and not got:
                raise DeviceTimeout(f"{self.name} unit {exp.unit}: no reply to {exp.what} within {self.timeout_s:g} s",
                                    device=self.name)
            raise self._err(FrameError, "short_frame", exp,
                            f"truncated reply: {len(got) + len(data)} of {len(got) + n} bytes", got + data)
        return data

    def _receive(self, exp: _Expect) -> bytes:
        deadline = time.monotonic() + self.timeout_s
        return self._receive_tcp(exp, deadline) if self.framing == "tcp" else self._receive_rtu(exp, deadline)

    def _receive_tcp(self, exp: _Expect, deadline: float) -> bytes:
        while True:
            head = self._read_exact(7, deadline, exp)
            rtid, proto, length, runit = struct.unpack(">HHHB", head)
            if proto != 0 or not 2 <= length <= 254:
                raise self._err(FrameError, "bad_header", exp, f"bad MBAP header (protocol {proto}, length {length})",
                                head)
            body = self._read_exact(length - 1, deadline, exp, head)
            if rtid != exp.tid:
                if rtid in self._recent_tids:  # a late reply to an earlier, timed-out request: drop it
                    self.stats.late_replies += 1
                    continue
                raise self._err(ReplyMismatch, "wrong_transaction", exp,
                                f"transaction id {rtid}, expected {exp.tid}", head + body)
            if runit != exp.unit:
                raise self._err(ReplyMismatch, "wrong_unit", exp, f"reply from unit {runit}", head + body)
            self._check_pdu(body, exp, head + body)
            if self._pending():  # a device sends nothing after its reply: these bytes make it suspect
                raise self._err(FrameError, "long_frame", exp, "bytes right behind the reply frame", head + body)
            return body

    def _receive_rtu(self, exp: _Expect, deadline: float) -> bytes:
        head = self._read_exact(3, deadline, exp)
        raddr, rfc, third = head
        if rfc == exp.fc | 0x80:
            total = 5  # unit, fc, exception code, crc
        elif rfc == exp.fc and exp.fc in (3, 4):
            total = 5 + third  # unit, fc, byte count, data, crc: the frame says its own length
        elif rfc == exp.fc:
            total = 8  # unit, fc, address, count, crc
        else:
            # not our function: read what is there, so the reason shown is the truest one
            rest = self.transport.read(256, min(deadline, time.monotonic() + max(self.frame_gap_s, 0.005)))
            frame = head + rest
            if len(frame) >= 4 and crc16(frame[:-2]) != frame[-2:]:
                raise self._err(ChecksumError, "bad_crc", exp, "CRC error (and unexpected function code)", frame)
            raise self._err(ReplyMismatch, "wrong_function", exp, f"function code {rfc:#04x}, expected {exp.fc:#04x}",
                            frame)
        frame = head + self._read_exact(total - 3, deadline, exp, head)
        if crc16(frame[:-2]) != frame[-2:]:
            raise self._err(ChecksumError, "bad_crc", exp, "CRC error", frame)
        if raddr != exp.unit:
            raise self._err(ReplyMismatch, "wrong_unit", exp, f"reply from unit {raddr}", frame)
        # RTU frames end with a silence: bytes right after this one mean it was not a single reply
        trailing = self.transport.read(1, time.monotonic() + self.frame_gap_s)
        if trailing:
            raise self._err(FrameError, "long_frame", exp, "bytes trailing the reply frame", frame + trailing)
        body = frame[1:-2]
        self._check_pdu(body, exp, frame)
        return body

    def _check_pdu(self, body: bytes, exp: _Expect, frame: bytes) -> None:
        """The PDU answers our request: function code, length, byte count, write echo."""
        if not body:
            raise self._err(FrameError, "short_frame", exp, "empty PDU", frame)
        if body[0] == exp.fc | 0x80:
            if len(body) != 2:
                raise self._err(FrameError, "short_frame" if len(body) < 2 else "long_frame", exp,
                                "exception reply of wrong length", frame)
            code = body[1]
            self.stats.exceptions += 1
            name = EXCEPTION_NAMES.get(code, "unknown exception")
            raise DeviceException(f"{self.name} unit {exp.unit}: {exp.what} refused (exception {code}: {name})",
                                  code, device=self.name)
        if body[0] != exp.fc:
            raise self._err(ReplyMismatch, "wrong_function", exp, f"function code {body[0]:#04x}, expected {exp.fc:#04x}",
                            frame)
        if exp.fc in (3, 4):
            if len(body) < 2:
                raise self._err(FrameError, "short_frame", exp, "no byte count", frame)
            if body[1] != 2 * exp.count:
                raise self._err(FrameError, "byte_count", exp, f"byte count {body[1]}, expected {2 * exp.count}", frame)
        if len(body) != exp.pdu_len:
            reason = "short_frame" if len(body) < exp.pdu_len else "long_frame"
            raise self._err(FrameError, reason, exp, f"PDU of {len(body)} bytes, expected {exp.pdu_len}", frame)
        if exp.fc == 16:
            raddr, rcount = struct.unpack(">HH", body[1:5])
            if raddr != exp.address or rcount != exp.count:
                raise self._err(ReplyMismatch, "wrong_echo", exp, f"write acknowledged as {raddr}+{rcount}", frame)

    def _decode(self, body: bytes, exp: _Expect):
        reply = self._decoder.decode(body)
        if reply is None:
            raise self._err(FrameError, "bad_header", exp, "undecodable reply", body)
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
