"""Fault injection for the simulated devices, from configuration or from tests.

Protocol-level faults of a Modbus device (``DeviceFaults``, one per served device)
act in the Modbus server (velab.simulators.modbus_server); the streaming ADC's are
its own (velab.simulators.streaming_adc.FaultPlan); model-level faults (sensors,
flowmeter, valve) live in ``velab.simulators.rig_faults``. A ``FaultPlan`` bundles
what a sim config's ``[faults]`` says::

    [faults.flowmeter]          # protocol faults of "flowmeter", from the start
    exception_code = 6          # every request answered with exception 6
    count = 3                   # ... only the next 3 requests (omit: until cleared)
    [faults.rig]                # model faults from the start (RigFaults)
    stuck_channels = { 0 = 1.5 }     # channel 0 stuck from t = 1.5 s

    [[faults.schedule]]         # a fault at an instant of the run (velab.simulators.schedule)
    device = "pressure_adc"
    fault = { silent = true }
    at = "trigger+1.5"
    duration_s = 0.5

Modbus protocol faults (``DeviceFaults`` fields = scheduled fault names):
delay_s (reply delayed; longer than the client's timeout = a timeout followed by a
late reply), exception_code, corrupt_crc (last byte flipped: a bad CRC on RTU),
garble (every byte XOR 0x5A), silent (the device takes no request and sends no
reply), drop_reply (the request is carried out, its reply lost on the way back: a
written command takes effect), drop_request (the request is lost on the way: not
carried out, no reply), short_by (reply truncated by N bytes), extra_bytes (N junk
bytes after the reply), wrong_unit (reply from another unit id), disconnect
(scheduled only: the endpoint goes away; comes back at the end of the window, never
without a duration); qualifiers: count (only the next N requests), writes_only (only
write requests: commands and settings; polls go on).

``BrokenGateway``: a Modbus TCP gateway between a client and a simulated device that flips
bits of one register in read replies while a condition holds (a payload corruption: Modbus
TCP has no checksum, no protocol check can see it; docs/recording.md, "Redundant
measurements").
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field, fields

from velab.errors import ConfigError
from velab.simulators.sadc_device import FaultPlan as StreamFaults
from velab.simulators.schedule import parse_schedule


@dataclass
class DeviceFaults:
    """Protocol faults of one simulated Modbus device, from the start; mutate at run time."""

    delay_s: float = 0.0
    exception_code: int | None = None
    corrupt_crc: bool = False
    garble: bool = False
    silent: bool = False
    short_by: int = 0
    extra_bytes: int = 0
    wrong_unit: bool = False
    drop_reply: bool = False
    drop_request: bool = False
    writes_only: bool = False
    count: int | None = None
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)

    def active(self) -> bool:
        return bool(self.delay_s or self.exception_code or self.corrupt_crc or self.garble or self.silent
                    or self.short_by or self.extra_bytes or self.wrong_unit or self.drop_reply or self.drop_request)

    def consume(self, write: bool = False) -> bool:
        """Called once per request: True if the fault applies to this one (``writes_only``: to writes only)."""
        with self._lock:
            if not self.active() or (self.writes_only and not write):
                return False
            if self.count is None:
                return True
            if self.count <= 0:
                return False
            self.count -= 1
            return True

    def as_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)
                if not f.name.startswith("_") and f.name not in ("count", "writes_only") and getattr(self, f.name)}

    def clear(self) -> None:
        self.delay_s, self.exception_code = 0.0, None
        self.corrupt_crc = self.garble = self.silent = self.wrong_unit = False
        self.drop_reply = self.drop_request = self.writes_only = False
        self.short_by = self.extra_bytes = 0
        self.count = None

    def set(self, **kw) -> "DeviceFaults":
        names = {f.name for f in fields(self) if not f.name.startswith("_")}
        for k, v in kw.items():
            if k not in names:
                raise ConfigError(f"unknown device fault {k!r} (known: {', '.join(sorted(names))})")
            setattr(self, k, v)
        return self


_RIG_KEYS = {"stuck_channels", "channel_mA", "flow_nan", "flow_value", "flow_stuck_at",
             "flow_alarm_bits", "valve_fault_after_s", "valve_fault_bits", "valve_warning_bits"}


@dataclass
class FaultPlan:
    devices: dict = field(default_factory=dict)  # device name -> dict of DeviceFaults fields
    rig: dict = field(default_factory=dict)  # RigFaults fields
    schedule: list = field(default_factory=list)  # the raw [[faults.schedule]] tables (checked by the bench)

    @classmethod
    def from_dict(cls, d: dict | None, where: str = "[faults]") -> "FaultPlan":
        d = dict(d or {})
        rig = d.pop("rig", {}) or {}
        schedule = d.pop("schedule", [])
        if not isinstance(rig, dict):
            raise ConfigError(f"{where}.rig: must be a table")
        unknown = sorted(set(rig) - _RIG_KEYS)
        if unknown:
            raise ConfigError(f"{where}.rig: unknown key {unknown[0]!r} (known: {', '.join(sorted(_RIG_KEYS))})")
        for key in ("stuck_channels", "channel_mA"):
            if key in rig:
                try:
                    rig[key] = {int(k): float(v) for k, v in rig[key].items()}
                except (AttributeError, TypeError, ValueError):
                    raise ConfigError(f"{where}.rig.{key}: must be a table {{channel = number}}") from None
        for name, faults in d.items():
            if not isinstance(faults, dict):
                raise ConfigError(f"{where}.{name}: must be a table of device faults")
            _validate_device_faults(faults, f"{where}.{name}")
        if not isinstance(schedule, list):
            raise ConfigError(f"{where}.schedule: must be an array of tables ([[faults.schedule]])")
        return cls(devices=d, rig=rig, schedule=schedule)

    def apply(self, rig_sim, device_faults: dict) -> None:
        for k, v in self.rig.items():
            setattr(rig_sim.faults, k, v)
        for name, kw in self.devices.items():
            if name not in device_faults:
                raise ConfigError(f"[faults.{name}]: no such simulated device (have: {', '.join(device_faults)})")
            try:
                device_faults[name].set(**kw)
            except ValueError as exc:  # another kind's fault names (the streaming ADC's FaultPlan)
                raise ConfigError(f"[faults.{name}]: {exc}") from None

    def scheduled(self, devices: dict[str, str], where: str = "[faults]") -> list[dict]:
        """The checked schedule; ``devices`` maps names to kinds (plus "rig")."""
        return parse_schedule(self.schedule, devices, where)


def _validate_device_faults(faults: dict, where: str) -> None:
    """Modbus protocol faults, or the streaming ADC's (velab.simulators.sadc_device.FaultPlan)."""
    try:
        DeviceFaults().set(**faults)
        return
    except ConfigError as exc:
        first = ConfigError(f"{where}: {exc}")
    try:
        StreamFaults().set(**faults)
    except (ValueError, TypeError):
        raise first from None


class BrokenGateway:
    """A Modbus TCP gateway that corrupts read replies' payloads: the fault no protocol check can see.

    Sits between a client and a Modbus TCP server (a simulated device): every request goes through
    unchanged; in the reply to a read (function 3 or 4) that covers ``register``, that register's
    word is XORed with ``xor`` while ``active()`` is true (asked once per reply, e.g. "the valve is
    mid-stroke"). MBAP header, length, transaction id, unit and function code stay as they were, and
    Modbus TCP has no checksum: the client gets a well-formed reply with a plausible wrong value
    (a valve position's float32 high word ^ 0x0080 halves or doubles it: 50 % open reads 100 %).
    ``corrupted`` counts the replies changed. Real sockets, one thread per direction per connection.
    """

    def __init__(self, upstream: tuple[str, int], register: int, xor: int, active=lambda: True,
                 host: str = "127.0.0.1"):
        import socket

        self.upstream, self.register, self.xor, self.active = upstream, int(register), int(xor) & 0xFFFF, active
        self.corrupted = 0
        self._listener = socket.create_server((host, 0))
        self.host, self.port = host, self._listener.getsockname()[1]
        self._socks: list = []
        self._threads: list[threading.Thread] = []
        self._lock = threading.Lock()
        self._stopping = threading.Event()

    def start(self) -> "BrokenGateway":
        self._spawn(self._accept)
        return self

    def _spawn(self, fn, *args) -> None:
        th = threading.Thread(target=fn, args=args, name="velab-sim-gateway", daemon=True)
        with self._lock:
            self._threads.append(th)
        th.start()

    def _accept(self) -> None:
        import socket

        while not self._stopping.is_set():
            try:
                client, _ = self._listener.accept()
                server = socket.create_connection(self.upstream, timeout=5.0)
                server.settimeout(None)
            except OSError:
                return  # listener closed (stop) or the device is gone: the client sees a closed link
            pending: dict[int, tuple[int, int, int]] = {}  # transaction id -> (function, address, count)
            with self._lock:
                self._socks += [client, server]
            self._spawn(self._pump, client, server, pending, True)
            self._spawn(self._pump, server, client, pending, False)

    @staticmethod
    def _frame(sock) -> bytes | None:
        """One MBAP frame (header + PDU), or None when the link closed."""
        def exactly(n):
            buf = b""
            while len(buf) < n:
                chunk = sock.recv(n - len(buf))
                if not chunk:
                    return None
                buf += chunk
            return buf
        head = exactly(7)
        if head is None:
            return None
        body = exactly(max(0, int.from_bytes(head[4:6], "big") - 1))
        return None if body is None else head + body

    def _pump(self, src, dst, pending: dict, requests: bool) -> None:
        try:
            while True:
                frame = self._frame(src)
                if frame is None:
                    break
                tid, fc = int.from_bytes(frame[0:2], "big"), frame[7] if len(frame) > 7 else 0
                if requests:
                    if fc in (3, 4) and len(frame) >= 12:
                        pending[tid] = (fc, int.from_bytes(frame[8:10], "big"), int.from_bytes(frame[10:12], "big"))
                else:
                    frame = self._corrupt(frame, pending.pop(tid, None))
                dst.sendall(frame)
        except OSError:
            pass  # one side closed: close both (below), as a gateway losing a link does
        finally:
            for s in (src, dst):
                _shut(s)

    def _corrupt(self, frame: bytes, request) -> bytes:
        if request is None or frame[7] != request[0]:
            return frame  # an exception reply, or a reply to something else: untouched
        _, address, count = request
        k = self.register - address
        if not (0 <= k < count) or len(frame) < 9 + 2 * (k + 1) or not self.xor or not self.active():
            return frame
        i = 9 + 2 * k  # MBAP 7, function, byte count, then the registers
        word = int.from_bytes(frame[i:i + 2], "big") ^ self.xor
        self.corrupted += 1
        return frame[:i] + word.to_bytes(2, "big") + frame[i + 2:]

    def stop(self) -> None:
        self._stopping.set()
        for s in [self._listener] + self._socks:
            _shut(s)
        for th in list(self._threads):
            th.join(2.0)

    def __enter__(self) -> "BrokenGateway":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def _shut(sock) -> None:
    """shutdown() first: a close() alone does not wake a thread blocked in recv()/accept() on Linux."""
    import socket

    for call in (lambda: sock.shutdown(socket.SHUT_RDWR), sock.close):
        try:
            call()
        except OSError:
            pass
