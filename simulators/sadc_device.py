"""Simulated SADC-4 streaming ADC, the device without I/O: command handling, sampling, frames, faults.

``SADCDevice`` turns command lines into replies and, while streaming, the device
clock into data frames (velab.drivers.sadc_protocol codec), with the faults of a
``FaultPlan`` (frame numbers since START) and of the rig's fault schedule (clock
instants: silent, corrupt, corrupt_every, drop, garbage, disconnect). The I/O
(TCP listener, pty) is velab.simulators.streaming_adc.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from velab.drivers.sadc_protocol import (
    ERR_BAD_ARGUMENT,
    ERR_BUSY,
    ERR_LINK_TOO_SLOW,
    ERR_UNKNOWN_COMMAND,
    ERROR_NAMES,
    FLAG_CLIP,
    FLAG_INVALID,
    FLAG_OVERRUN,
    MAX_BLOCK,
    MAX_CHANNELS,
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
    frames_silenced: int = 0  # generated while a scheduled silence was on (lost; next frame flagged OVERRUN)
    garbage_bytes: int = 0
    disconnects: int = 0
    last_stop_total: int = 0


class SADCDevice:
    """The device's state machine (no I/O). Subclasses serve it on a link."""

    IDN = "VELAB,SADC-4"

    def __init__(self, source: Source | None = None, *, faults: "FaultPlan | None" = None, serial_no: str = "SIM0001",
                 firmware: str = "1.0", clock=None, schedule=None, name: str = "streaming_adc"):
        self.source = source or default_source
        self.faults = faults or FaultPlan()
        self.serial_no = serial_no
        self.firmware = firmware
        self.clock = clock  # optional: source time = clock.now() at START + device time
        self.schedule = schedule  # optional: a velab.simulators.schedule.FaultSchedule
        self.name = name  # this device's name in the schedule
        self._t_source0 = 0.0
        self.stats = SimStats()
        self._rng = np.random.default_rng(self.faults.seed)
        self._disconnects_left = self.faults.disconnects
        self._sched_disconnect = False  # a scheduled disconnect reached by the device clock
        self._reset_config()

    # ------------------------------------------------------------ scheduled faults

    def scheduled(self, t: float | None = None) -> dict:
        """The scheduled faults active at clock time t (default: now); {} without a schedule."""
        sched = self.schedule
        if sched is None or not sched.entries(self.name):
            return {}
        if t is None:
            t = self.clock.now() if self.clock is not None else 0.0
        return sched.merged(self.name, t)

    def silent_now(self) -> bool:
        return bool(self.scheduled().get("silent"))

    def disconnected_now(self) -> bool:
        return bool(self.scheduled().get("disconnect"))

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
        sched = self.schedule is not None and bool(self.schedule.entries(self.name))
        for j in range(n_frames):
            n = self.frame_no
            first = self.index
            # scheduled faults at the frame's first sample, on the clock's axis
            sf = self.scheduled(self._t_source0 + first / self.rate_hz) if sched else {}
            if sf.get("disconnect"):
                self._sched_disconnect = True  # the link drops here; this frame is never made
                return j
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
            if sf.get("silent"):  # the device stops sending; its FIFO overflows meanwhile
                self._flag_overrun = True
                st.frames_silenced += 1
                st.samples_lost += k
                continue
            if FaultPlan._hit(n, f.drop_frames, f.drop_every) or sf.get("drop"):
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
            ce = sf.get("corrupt_every", 0)
            if FaultPlan._hit(n, f.corrupt_frames, f.corrupt_every) or sf.get("corrupt") or (ce and n % ce == ce - 1):
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
            if (f.garbage_every and n % f.garbage_every == f.garbage_every - 1) or sf.get("garbage"):
                junk = bytearray(self._rng.integers(0, 256, int(self._rng.integers(3, 41)), dtype=np.uint8).tobytes())
                junk[0:2] = b"\xa5\x5a"
                out += junk
                st.garbage_bytes += len(junk)
        return n_frames



def _fmt_rate(hz: float) -> str:
    return f"{hz:.3f}".rstrip("0").rstrip(".")
