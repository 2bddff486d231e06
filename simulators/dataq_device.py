"""Simulated DATAQ DI-series instrument, the device without I/O: commands, scanning, the binary stream, faults.

Speaks the protocol of velab.drivers.dataq_protocol byte for byte (the vendor's "Data Acquisition Instrument
Command Protocol", 2019): commands end in CR and echo while not scanning, ``start`` never echoes, ``stop``
always does, nothing else echoes while scanning (p.16); ``info`` answers with the model's identity (p.20);
the stream is two bytes per scan-list position (pp.60-68) in packets of the ``ps`` size (p.21); an overflow
ends the stream with ``stop 01`` (p.50). The I/O (pty, TCP) is velab.simulators.dataq_sim.

Where the document is silent the simulator chooses, and says so: a command a model lacks (``dec`` on a
DI-1100, an unknown word) is answered ``<line> command not found`` (the document names a "command not found
response", p.38, without its bytes); out-of-range ``srate`` values are clamped to the model's bounds; only the
binary output mode is simulated (``encode 1`` echoes, the stream stays binary).

Analogue inputs: ``source(t) -> (n, >= inputs)`` in mA (velab.simulators.rig.SimulatedRig.analog_inputs),
turned into volts through each input's shunt (``shunt_ohm``; None: the source value is volts) and quantised
to the model's counts. Digital outputs call ``on_digital(line, level, t)`` (t on the source's time axis).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from velab.drivers import dataq_protocol as dq

Source = Callable[[np.ndarray], np.ndarray]


def default_source(t: np.ndarray) -> np.ndarray:
    """4 inputs in mA: pressure 12 mA with a 2.5 Hz oscillation of 2 mA, valve position 20 mA, 4 and 12 mA."""
    t = np.asarray(t, dtype=float)
    out = np.empty((t.size, 4))
    out[:, 0] = 12.0 + 2.0 * np.sin(2 * np.pi * 2.5 * t)
    out[:, 1] = 20.0
    out[:, 2] = 4.0
    out[:, 3] = 12.0
    return out


@dataclass
class DataqFaults:
    """Faults to inject; scan numbers count scans generated since ``start`` (0-based)."""

    silent: bool = False  # no replies, no data (a hung device, the link still open)
    stall_after_scans: int | None = None  # the stream stops there (the device still answers ``stop``)
    drop_byte_at_scans: frozenset = frozenset()  # one byte of these scans never arrives (framing lost)
    garbage_at_scans: frozenset = frozenset()  # junk bytes inserted after these scans
    garbage_bytes: int = 7
    overflow_after_scans: int | None = None  # the 1024-sample buffer overflows: ``stop 01``, scanning ends
    disconnect_after_scans: int | None = None  # the link drops (TCP close / the pty vanishes)
    disconnects: int = 1
    reconnect_delay_s: float = 0.2
    seed: int = 1

    def set(self, **kw) -> "DataqFaults":
        for k, v in kw.items():
            if k not in self.__dataclass_fields__:
                raise ValueError(f"unknown DATAQ fault {k!r} (known: {', '.join(self.__dataclass_fields__)})")
            setattr(self, k, frozenset(v) if isinstance(getattr(self, k), frozenset) else v)
        return self

    def clear(self) -> None:
        for k, f in self.__dataclass_fields__.items():
            setattr(self, k, f.default_factory() if callable(f.default_factory) else f.default)


@dataclass
class DataqSimStats:
    connections: int = 0
    commands: int = 0
    starts: int = 0
    scans_generated: int = 0
    bytes_dropped: int = 0
    garbage_bytes: int = 0
    overflows: int = 0
    disconnects: int = 0
    douts: list = field(default_factory=list)  # (t, dout value) of every dout


class DataqDevice:
    """The instrument's state machine (no I/O). ``handle_line`` answers commands; ``generate`` makes scans."""

    def __init__(self, model: str = "DI-2108", source: Source | None = None, *, shunt_ohm=(250.0, 250.0),
                 serial_no: str = "5A1B2C3D", firmware: str = "1.21", on_digital=None,
                 faults: DataqFaults | None = None, clock=None, schedule=None, name: str = "dataq",
                 digital_inputs: int = 0):
        self.spec = dq.model(model)
        self.source = source or default_source
        shunts = list(shunt_ohm or ())
        self.shunt_ohm = [shunts[i] if i < len(shunts) else None for i in range(self.spec.analog_inputs)]
        self.serial_no = serial_no
        self.firmware = firmware
        self.on_digital = on_digital
        self.faults = faults or DataqFaults()
        self.clock = clock
        self.schedule = schedule
        self.name = name
        self.digital_inputs = digital_inputs  # levels applied to the ports configured as inputs
        self.stats = DataqSimStats()
        self._rng = np.random.default_rng(self.faults.seed)
        self._disconnects_left = self.faults.disconnects
        self.reset()

    def reset(self) -> None:
        """Power-up state (p.39: the scan list holds analog input 0 only)."""
        self.scanning = False
        self.encode = 0
        self.ps_code = 0
        self.slist = [0]
        self.srate = 60000 if self.spec.dec_max == 1 else 375
        self.dec = 1
        self.deca = 1
        self.endo = 0
        self.dout = 0
        self.index = 0
        self.counter = 0
        self.t_start: float | None = None

    # ------------------------------------------------------------ time and scheduled faults

    def source_time(self) -> float:
        """Now on the source's time axis: the simulation clock's, or without one the device time since the
        last start (0 at ``start``)."""
        if self.clock is not None:
            return float(self.clock.now())
        return time.monotonic() - self.t_start if self.t_start is not None else 0.0

    def clock_scale(self) -> float:
        return float(getattr(self.clock, "scale", 1.0) or 1.0) if self.clock is not None else 1.0

    def scheduled(self) -> dict:
        s = self.schedule
        if s is None or not s.entries(self.name):
            return {}
        return s.merged(self.name, self.source_time())

    def silent_now(self) -> bool:
        return self.faults.silent or bool(self.scheduled().get("silent"))

    def disconnected_now(self) -> bool:
        return bool(self.scheduled().get("disconnect"))

    @property
    def rate_hz(self) -> float:
        return self.spec.dividend / (self.srate * self.dec * self.deca)

    @property
    def packet_size(self) -> int:
        return dq.PACKET_SIZES[self.ps_code]

    @property
    def scan_bytes(self) -> int:
        return 2 * len(self.slist)

    # ------------------------------------------------------------ commands

    def handle_line(self, line: bytes) -> bytes | None:
        """One command line (CR stripped) -> the reply bytes (None: no reply)."""
        self.stats.commands += 1
        text = line.strip(b"\n\x00 ").decode("ascii", "replace")
        if not text:
            return None
        words = text.split()
        cmd, args = words[0], words[1:]
        nums = []
        for a in args:
            try:
                nums.append(int(a))
            except ValueError:
                nums.append(None)
        reply = self._command(cmd, args, nums, text)
        if self.scanning and cmd != "stop":
            return None  # nothing echoes while scanning (p.16)
        return None if reply is None else reply.encode("ascii") + dq.CR

    def _command(self, cmd: str, args: list, nums: list, text: str) -> str | None:
        spec = self.spec
        n0 = nums[0] if nums else None
        if cmd == "stop":
            self.scanning = False
            return "stop"
        if cmd == "start" and (not args or n0 == 0):
            if not self.scanning:
                self._begin()
            return None  # never echoes (p.49)
        if self.scanning and cmd not in ("dout",):
            return None
        if cmd == "info" and n0 is not None:
            answer = {0: "DATAQ", 1: spec.number, 2: dq.firmware_code(self.firmware), 6: self.serial_no,
                      9: str(int(spec.dividend))}.get(n0)
            return text if answer is None else f"info {n0} {answer}"
        if cmd == "encode" and n0 in (0, 1):
            self.encode = n0
            return text
        if cmd == "ps":
            if not args:
                return f"ps {self.packet_size}"
            if n0 is not None and 0 <= n0 < len(dq.PACKET_SIZES):
                self.ps_code = n0
            return text
        if cmd == "slist" and len(nums) == 2 and None not in nums:
            pos, word = nums
            if self._slist_word_ok(word):
                if pos == 0:
                    self.slist = [word]  # writing position 0 resets the member count to 1 (p.39)
                elif pos < len(self.slist):
                    self.slist[pos] = word
                elif pos == len(self.slist) and pos < spec.slist_max:
                    self.slist.append(word)
            return text
        if cmd == "srate" and n0 is not None:
            n_an = sum(1 for w in self.slist if (w & 0xF) < 8)
            self.srate = min(max(n0, spec.srate_lo(n_an)), dq.SRATE_MAX)
            return text
        if cmd == "dec" and spec.dec_max > 1 and n0 is not None:
            self.dec = min(max(n0, 1), spec.dec_max)
            return text
        if cmd == "deca" and spec.deca and n0 is not None:
            self.deca = min(max(n0, 1), 40000)
            return text
        if spec.digital_io:
            if cmd == "endo" and n0 is not None and 0 <= n0 <= 0x7F:
                self._set_dout(0)  # every port re-initialised (p.57): the old switches open
                self.endo = n0
                return text
            if cmd == "dout" and n0 is not None and 0 <= n0 <= 0x7F:
                self._set_dout(n0)
                return text
            if cmd == "din" and not args:
                return f"din {self.din_state()}"
        if cmd in ("filter", "led", "reset", "ffl") and args:
            if cmd == "reset" and n0 == 1:
                self.counter = 0
            return text
        return f"{text} command not found"

    def _slist_word_ok(self, word: int) -> bool:
        fn = word & 0xF
        if fn < 8:
            return fn < self.spec.analog_inputs and word >> 4 == 0
        if self.spec.stream_digital != "word":
            return False
        return word == dq.SLIST_DIGITAL_IN or word == dq.SLIST_COUNT or (fn == 9 and 1 <= word >> 8 <= 12)

    def _set_dout(self, value: int) -> None:
        t = self.source_time()
        old = self.dout
        self.dout = value & self.endo
        self.stats.douts.append((t, self.dout))
        if self.on_digital is not None:
            for line in range(self.spec.digital_lines):
                bit = 1 << line
                if self.endo & bit and (old ^ self.dout) & bit:
                    self.on_digital(line, bool(self.dout & bit), t)

    def din_state(self) -> int:
        """Switches read back their state, inputs the level applied (p.58)."""
        return (self.dout & self.endo) | (self.digital_inputs & ~self.endo & 0x7F)

    # ------------------------------------------------------------ scanning

    def _begin(self) -> None:
        self.scanning = True
        self.index = 0
        self.t_start = time.monotonic()
        self._t_source0 = float(self.clock.now()) if self.clock is not None else 0.0
        self.stats.starts += 1

    def due_scans(self) -> int:
        """Scans the device clock says are due now (real time, or the simulation clock)."""
        if self.clock is not None:
            elapsed = self.clock.now() - self._t_source0
        else:
            elapsed = time.monotonic() - self.t_start
        return max(0, int(elapsed * self.rate_hz) - self.index)

    def next_scan_wait_s(self) -> float:
        """Host seconds until the next scan is due."""
        due_t = (self.index + 1) / self.rate_hz
        if self.clock is not None:
            return max(0.0, (due_t - (self.clock.now() - self._t_source0)) / self.clock_scale())
        return max(0.0, self.t_start + due_t - time.monotonic())

    def generate(self, n: int) -> bytes:
        """The next n scans as stream bytes (with the scan-numbered faults applied)."""
        f = self.faults
        for limit in (f.stall_after_scans, f.overflow_after_scans,
                      f.disconnect_after_scans if self._disconnects_left > 0 else None):
            if limit is not None:
                n = min(n, max(0, limit - self.index))
        if n <= 0:
            return b""
        t = self._t_source0 + (self.index + np.arange(n)) / self.rate_hz
        ma = np.atleast_2d(np.asarray(self.source(t), dtype=float))
        din = self.din_state()
        cols = []
        for w in self.slist:
            fn = w & 0xF
            if fn < 8:
                shunt = self.shunt_ohm[fn]
                volts = ma[:, fn] * (shunt / 1000.0) if shunt else ma[:, fn]
                counts = self.spec.counts(volts)
                dig = np.full(n, din & 0x3) if (self.spec.stream_digital == "position0" and not cols) else None
                cols.append(dq.encode_words(self.spec, counts[:, None], dig)[:, 0])
            elif fn == 8:
                cols.append(np.full(n, dq.digital_word(din), dtype=np.uint16))
            elif fn == 9:
                cols.append(np.full(n, 0x8000, dtype=np.uint16))  # rate 0 Hz: (counts + 32768) / 65536 x range (p.60)
            else:
                cols.append(np.full(n, (self.counter - 32768) & 0xFFFF, dtype=np.uint16))  # counter (p.60)
        data = bytearray(np.column_stack(cols).astype("<u2").tobytes())
        sb = self.scan_bytes
        # faults inside the batch, from its last scan back (offsets stay valid)
        hits = sorted({s for s in f.drop_byte_at_scans | f.garbage_at_scans if self.index <= s < self.index + n},
                      reverse=True)
        for s in hits:
            off = (s - self.index) * sb
            if s in f.garbage_at_scans:
                junk = self._rng.integers(0, 256, f.garbage_bytes, dtype=np.uint8).tobytes()
                data[off + sb:off + sb] = junk
                self.stats.garbage_bytes += len(junk)
            if s in f.drop_byte_at_scans:
                del data[off + sb // 2]
                self.stats.bytes_dropped += 1
        self.index += n
        self.stats.scans_generated += n
        return bytes(data)

    def fault_point(self) -> str | None:
        """What the scan-numbered faults say now that the scans before them are made: "overflow",
        "disconnect", "stall" or None."""
        f = self.faults
        if f.overflow_after_scans is not None and self.index >= f.overflow_after_scans:
            return "overflow"
        if (f.disconnect_after_scans is not None and self._disconnects_left > 0
                and self.index >= f.disconnect_after_scans):
            return "disconnect"
        if f.stall_after_scans is not None and self.index >= f.stall_after_scans:
            return "stall"
        return None

    def overflow(self) -> bytes:
        """The buffer overflowed: scanning stops, ``stop 01`` ends the final response (p.50)."""
        self.scanning = False
        self.stats.overflows += 1
        return dq.OVERFLOW_REPORT
