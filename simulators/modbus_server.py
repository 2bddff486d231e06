"""The simulators' Modbus server layer: the only simulator module that imports pymodbus.

``ModbusDeviceServer`` serves one simulated device (anything with ``layout()``,
``read(address, count)``, ``write(address, values)``, ``unit`` and ``faults``) on one
endpoint, in a daemon thread with its own asyncio loop:

* ``transport="tcp"``: Modbus TCP on host:port (port 0 = ephemeral);
* ``transport="rtu-socket"``: RTU framing over a TCP listener, reached with
  ``socket://host:port`` (pyserial URL);
* ``transport="rtu"``: RTU on a serial device path, e.g. the device end of a
  :class:`velab.simulators.pty_bridge.PtyPair`.

Register values are produced at request time by the device's ``read`` (no updater
thread). Faults act here, decided once per request in the pymodbus ``action``
callback from the device's ``DeviceFaults`` (from the start) and the rig's fault
schedule at the request's instant: a lost request or a silent device (nothing is
carried out), reply delay and exception replies in the action; corrupted / garbled /
truncated / padded / wrong-unit / lost replies in ``trace_packet``. A reply fault
that begins while the request is carried out (anchored at the instant that request
makes: the trigger) applies to its reply: the command took effect, its reply is lost. A delay blocks this server's loop (a single-threaded device, like a
real one): requests queue behind it and every reply keeps its own transaction id.
"""

from __future__ import annotations

import asyncio
import logging
import os
import socket
import stat
import threading

from pymodbus.constants import ExcCodes
from pymodbus.exceptions import ModbusIOException, NoSuchIdException
from pymodbus.framer import FramerRTU, FramerType
from pymodbus.pdu import ExceptionResponse
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler
from pymodbus.simulator import DataType, SimData, SimDevice

from velab.drivers.modbus import crc16
from velab.simulators.schedule import MODBUS_REPLY_FAULTS, merge_faults

log = logging.getLogger(__name__)

# pymodbus logs every garbled frame at ERROR level; fault-injection tests make many.
logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


def _shut_sockets_on_port(port: int) -> None:
    """Shut down every TCP socket of this process bound to ``port`` (Linux /proc).

    pymodbus does not always close a client connection it accepted just before shutting
    down: that connection would stay open and silent, and a simulated disconnect would look
    like a timeout. A shutdown (FIN) makes the client see the connection drop; the fd itself
    stays with its owner."""
    try:
        fds = os.listdir("/proc/self/fd")
    except OSError:
        return
    for name in fds:
        try:
            fd = int(name)
            if not stat.S_ISSOCK(os.fstat(fd).st_mode):
                continue
            s = socket.socket(fileno=fd)
        except (OSError, ValueError):
            continue
        try:
            if s.family in (socket.AF_INET, socket.AF_INET6) and s.type == socket.SOCK_STREAM \
                    and s.getsockname()[1] == port:
                s.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        finally:
            s.detach()


class _InOrderHandler(ServerRequestHandler):
    """One client connection that answers every request it receives, one after another.

    pymodbus (3.16) decodes one frame per read from the socket and clears its receive buffer when
    it replies, so a request that arrives together with another (a client whose previous request
    timed out while this device was busy, on a loaded host) is dropped without a reply and never
    carried out: a TRIGGER lost that way read back as "not started". A real device queues what
    arrives and answers each request in turn; so does this handler."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._queue: asyncio.Queue | None = None
        self._answering: asyncio.Task | None = None

    def callback_disconnected(self, exc: Exception | None) -> None:
        super().callback_disconnected(exc)
        if self._answering is not None:
            self._answering.cancel()  # what was queued goes with the connection, as on a device

    def callback_data(self, data: bytes, addr: tuple | None = None) -> int:
        used = 0
        while used < len(data):
            try:
                n, pdu = self.framer.handleFrame(self.trace_packet(False, data[used:]), 0, 0)
            except ModbusIOException as exc:  # undecodable: pymodbus's own answer, the rest dropped
                self._enqueue(ExceptionResponse(0x00 if exc.fcode is None else exc.fcode,
                                                exception_code=ExcCodes.ILLEGAL_FUNCTION,
                                                device_id=exc.dev_id, transaction=exc.transaction_id), addr)
                return len(data)
            if n == 0:
                break  # an incomplete frame: kept until the rest arrives
            used += n
            if pdu is not None:
                self._enqueue(pdu, addr)
        return used

    def _enqueue(self, item, addr) -> None:
        if self._queue is None:
            self._queue = asyncio.Queue()
            self._answering = self.loop.create_task(self._answer_in_turn())
        self._queue.put_nowait((item, addr))

    async def _answer_in_turn(self) -> None:
        while True:
            item, addr = await self._queue.get()
            if isinstance(item, ExceptionResponse):
                self.server_send(item, addr)
            else:
                await self._answer(item, addr)

    async def _answer(self, pdu, addr) -> None:
        # as pymodbus's handle_request, for this request rather than the handler's "last" one
        try:
            response = await pdu.datastore_update(self.server.context, pdu.dev_id)
        except NoSuchIdException:
            if self.server.ignore_missing_devices:
                return
            response = ExceptionResponse(pdu.function_code, ExcCodes.GATEWAY_NO_RESPONSE)
        except Exception:  # noqa: BLE001 - pymodbus answers a datastore failure so
            log.exception("simulated device request failed")
            response = ExceptionResponse(pdu.function_code, ExcCodes.DEVICE_FAILURE)
        response.transaction_id = pdu.transaction_id
        response.dev_id = pdu.dev_id
        self.server_send(response, addr)

    def send(self, data: bytes, addr: tuple | None = None) -> None:
        kept = self.recv_buffer  # pymodbus clears it on sending: a partial next request would be lost
        super().send(data, addr)
        self.recv_buffer = kept


class _RtuFrames(FramerRTU):
    """RTU frames are delimited by silence on the wire, and pymodbus takes all it has read as one
    frame (the rest dropped). Frames that reached one read together (a starved host; on the line
    they were a timeout apart) are decoded each at its own length here."""

    def decode(self, data: bytes) -> tuple[int, int, int, bytes]:
        for start in range(len(data)):
            if len(data) - start < self.MIN_SIZE:
                return 0, 0, 0, self.EMPTY
            if not (pdu_class := self.decoder.lookupPduClass(data[start:])):
                continue  # hunting past garbage, as pymodbus does
            dev_id = int(data[start])
            if not (size := pdu_class.calculateRtuFrameSize(data[start:])) or len(data) < start + size:
                return 0, dev_id, 0, self.EMPTY  # wait for more
            end = start + size
            if not FramerRTU.check_CRC(data[start:end - 2], int.from_bytes(data[end - 2:end], "big")):
                return len(data), 0, 0, self.EMPTY  # garbage: dropped, as pymodbus does
            return end, dev_id, 0, data[start + 1:end - 2]
        return 0, 0, 0, self.EMPTY


class _TcpServer(ModbusTcpServer):
    def callback_new_connection(self):
        return _InOrderHandler(self, self.trace_packet, self.trace_pdu, self.trace_connect)


class _SerialServer(ModbusSerialServer):
    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.framer = _RtuFrames

    def callback_new_connection(self):
        return _InOrderHandler(self, self.trace_packet, self.trace_pdu, self.trace_connect)


class ModbusDeviceServer:
    def __init__(self, device, transport: str = "tcp", *, host: str = "127.0.0.1", port: int = 0,
                 serial_path: str | None = None, baudrate: int = 19200, wire_delay: bool = False):
        if transport not in ("tcp", "rtu-socket", "rtu"):
            raise ValueError(f"transport must be tcp, rtu-socket or rtu, got {transport!r}")
        if transport == "rtu" and not serial_path:
            raise ValueError("transport 'rtu' needs serial_path")
        self.device = device
        self.transport = transport
        self.host = host
        self.port = port
        self.serial_path = serial_path
        self.baudrate = baudrate
        self.wire_delay = wire_delay
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._server = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._now: dict = {}  # the faults decided for the request being answered
        self._stopping = threading.Event()
        self._held: socket.socket | None = None  # the port, held while disconnected (disconnect)
        self.requests = 0

    # ------------------------------------------------------------ endpoint
    @property
    def endpoint(self) -> str:
        if self.transport == "tcp":
            return f"tcp://{self.host}:{self.port}"
        if self.transport == "rtu-socket":
            return f"socket://{self.host}:{self.port}"
        return self.serial_path

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    # ------------------------------------------------------------ pymodbus glue
    def _sim_device(self) -> SimDevice:
        blocks = [SimData(addr, count=n, values=0, datatype=DataType.REGISTERS) for addr, n in self.device.layout()]
        return SimDevice(id=self.device.unit, simdata=blocks, action=self._action)

    def _schedule(self):
        return getattr(getattr(self.device, "rig", None), "schedule", None)

    def _request_faults(self, write: bool) -> tuple[dict, frozenset]:
        """The faults that apply to this request as it arrives: the device's own, then the schedule's
        at this instant (each counted once); and the ids of the schedule entries taken."""
        dev = self.device
        now = dict(dev.faults.as_dict()) if dev.faults.consume(write) else {}
        sched = self._schedule()
        if sched is None:
            return now, frozenset()
        entries = sched.take(dev.name, dev.rig.clock.now(), write=write)
        now.update(merge_faults(entries))
        return now, frozenset(e.id for e in entries)

    def _reply_faults(self, write: bool, taken: frozenset) -> dict:
        """Reply faults of schedule entries that began while the request was carried out: a fault at
        the trigger instant (marked by the TRIGGER being executed) hits the reply to that TRIGGER."""
        sched = self._schedule()
        if sched is None:
            return {}
        later = sched.take(self.device.name, self.device.rig.clock.now(), write=write, exclude=taken,
                           kinds=MODBUS_REPLY_FAULTS)
        return {k: v for k, v in merge_faults(later).items() if k in MODBUS_REPLY_FAULTS}

    async def _action(self, fc, start, address, count, registers, values):
        self.requests += 1
        write = values is not None
        now, taken = self._request_faults(write)
        self._now = now
        if now.get("silent") or now.get("drop_request") or now.get("disconnect"):
            return None  # the device never sees the request: nothing is carried out (and no reply: _trace_packet)
        if now.get("delay_s"):
            # blocking on purpose (a slow device holds its line); stop() ends it. (A sleep of the time left,
            # computed after the loop's own check, went negative on a loaded host: ValueError, a failed request.)
            self._stopping.wait(now["delay_s"])
        if now.get("exception_code"):
            return ExcCodes(now["exception_code"])
        if self.wire_delay and self.transport != "tcp":
            # request + reply bytes on the wire (the pty bridge can do this instead)
            n_bytes = 8 + (5 + 2 * count if values is None else 8 + 2 * len(values))
            await asyncio.sleep(n_bytes * 10.0 / self.baudrate)
        try:
            if values:
                code = self.device.write(address, list(values))
                self._now = {**now, **self._reply_faults(write, taken)}
                return ExcCodes(code) if code else None
            live = self.device.read(address, count)
        except Exception:  # noqa: BLE001 - a simulator bug must show, as a device failure reply
            log.exception("simulated device %s failed", getattr(self.device, "name", "?"))
            return ExcCodes.DEVICE_FAILURE
        self._now = {**now, **self._reply_faults(write, taken)}
        off = address - start
        registers[off:off + count] = [int(v) & 0xFFFF for v in live]
        return None

    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        if not sending:
            return data
        now, self._now = self._now, {}
        if not now or not data:
            return data
        if now.get("silent") or now.get("disconnect") or now.get("drop_reply") or now.get("drop_request"):
            return b""
        rtu = self.transport != "tcp"
        if now.get("wrong_unit"):
            if rtu:
                body = bytes([(data[0] + 1) & 0xFF]) + data[1:-2]
                data = body + crc16(body)
            else:
                data = data[:6] + bytes([(data[6] + 1) & 0xFF]) + data[7:]
        if now.get("garble"):
            data = bytes((b ^ 0x5A) for b in data)
        if now.get("corrupt_crc"):
            data = data[:-1] + bytes([data[-1] ^ 0xFF])
        if now.get("short_by"):
            data = data[: max(1, len(data) - int(now["short_by"]))]
        if now.get("extra_bytes"):
            data = data + bytes((0xA5 + 7 * i) & 0xFF for i in range(int(now["extra_bytes"])))
        return data

    async def _main(self) -> None:
        kw = dict(trace_packet=self._trace_packet)
        try:
            if self.transport == "tcp":
                self._server = _TcpServer(self._sim_device(), address=(self.host, self.port), **kw)
            elif self.transport == "rtu-socket":
                self._server = _SerialServer(self._sim_device(), framer=FramerType.RTU,
                                                  port=f"socket://{self.host}:{self.port}", baudrate=self.baudrate, **kw)
            else:
                self._server = _SerialServer(self._sim_device(), framer=FramerType.RTU,
                                                  port=self.serial_path, baudrate=self.baudrate, **kw)
            await self._server.serve_forever(background=True)
            if self.transport != "rtu":
                self.port = self._server.transport.sockets[0].getsockname()[1]
        except BaseException as exc:  # noqa: BLE001 - reported to start()
            self._error = exc
            self._ready.set()
            return
        self._ready.set()
        await self._server.serving
        for _ in range(5):  # let the transports' close callbacks run: clients see the connection drop
            await asyncio.sleep(0.002)

    def _run(self) -> None:
        self._loop = asyncio.new_event_loop()
        try:
            self._loop.run_until_complete(self._main())
        finally:
            pending = asyncio.all_tasks(self._loop)  # e.g. a client still connected: its answering task
            for task in pending:
                task.cancel()
            if pending:
                self._loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
            self._loop.close()

    # ------------------------------------------------------------ lifecycle
    def start(self, timeout_s: float = 5.0) -> "ModbusDeviceServer":
        if self.running:
            return self
        self._stopping.clear()
        self._ready.clear()
        self._error = None
        self._thread = threading.Thread(target=self._run, name=f"modbus-sim-{self.endpoint}", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s):
            raise RuntimeError(f"simulated device server {self.endpoint} did not start within {timeout_s} s")
        if self._error is not None:
            self._thread.join(1.0)
            raise RuntimeError(f"cannot start simulated device server on {self.endpoint}: {self._error}") from self._error
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        self._release_port()
        if not self.running or self._loop is None:
            return
        self._stopping.set()  # ends an injected delay in progress
        fut = asyncio.run_coroutine_threadsafe(self._server.shutdown(), self._loop)
        try:
            fut.result(timeout_s)
        except Exception:  # noqa: BLE001 - shutting down anyway
            pass
        self._thread.join(timeout_s)
        self._thread = None
        if self.transport != "rtu":
            _shut_sockets_on_port(self.port)

    def disconnect(self) -> None:
        """Drop every client and stop listening (a device power-cycling or a cable pulled).

        The port stays this device's while it is down: a socket bound to it that does not listen refuses
        connections as the stopped server does, and the host gives the port to no one else meanwhile (on a
        loaded host another test's simulator took a freed port once, and the device could not come back)."""
        self.stop()
        if self.transport != "rtu":
            self._hold_port()

    def reconnect(self) -> None:
        """Listen again on the same endpoint (the new listener binds beside the held port, then it is let go)."""
        self.start()
        self._release_port()

    def _hold_port(self) -> None:
        family = socket.getaddrinfo(self.host, self.port, type=socket.SOCK_STREAM)[0][0]
        s = socket.socket(family, socket.SOCK_STREAM)
        # both the holder and the server's listener set SO_REUSEADDR: the listener may bind beside the holder
        # (neither listens at that instant), and the dropped connections' TIME_WAIT does not block the holder
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((self.host, self.port))
        except OSError:  # taken in the instant since the stop: nothing to hold, as before
            s.close()
            return
        self._held = s

    def _release_port(self) -> None:
        if self._held is not None:
            self._held.close()
            self._held = None

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()
