"""DATAQ Instruments DI-series command protocol: the pure codec (no I/O).

Written from the vendor's document "Data Acquisition Instrument Command Protocol" (DATAQ
Instruments, revised August 1, 2019, 72 pages; cited below as [Protocol p.N, "section"]).
Covers the models velab supports: DI-1100, DI-1110, DI-2108 (USB, CDC mode).

* Commands are ASCII, arguments decimal, separated by one space, ended by CR (0x0D); every command
  echoes while the instrument is not scanning, none echoes while it scans; ``start`` never echoes,
  ``stop`` always does [Protocol p.16, "Shared and USB-specific Protocol Command Usage"].
* The command buffer is very small: send a command only after the previous one's echo [p.16].
* Replies: the echoed command, a space, the response, CR (``info 1`` -> ``info 1 2108``) [p.21].
* Binary stream: two bytes per scan-list position, low byte first, in scan-list order, wrapping
  back to position 0; no header, no counter, no checksum [p.60, "Binary Stream Output Formats"].
* Buffer overflow: the instrument stops scanning and puts ``stop 01`` in the last seven bytes of its
  final response [p.50, "stop Command"].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

VENDOR_ID = 0x0683  # all models [Protocol p.8, PID/VID table]
CR = b"\r"
OVERFLOW_REPORT = b"stop 01"  # the last seven bytes of the final response after an overflow [p.50]
STOP_ECHO = b"stop\r"
ENCODE_BINARY = 0  # encode 0: binary output mode (default) [p.38]
PACKET_SIZES = (16, 32, 64, 128, 256, 512, 1024, 2048)  # ps 0..7 [p.20]
SLIST_DIGITAL_IN = 0x0008  # scan-list word of the digital-input ports [p.44, "DI-2108 and DI-1110 Scan List"]
SLIST_RATE = 0x0009  # low nibble of the rate channel (bits 8-11: its range) [p.44]
SLIST_COUNT = 0x000A  # counter channel [p.44]
RATE_RANGES_HZ = (50_000, 20_000, 10_000, 5_000, 2_000, 1_000, 500, 200, 100, 50, 20, 10)  # code 1..12 [p.47]
SRATE_MAX = 65535  # every model [p.48, "srate Variable Table"]


@dataclass(frozen=True)
class ModelSpec:
    """One instrument model, every number from the protocol document (pages in the comments)."""

    name: str  # "DI-2108"
    number: str  # what ``info 1`` answers: "2108" [p.20]
    pid_cdc: int  # USB product id in CDC mode [p.8]
    analog_inputs: int
    adc_bits: int  # 12: counts in bits 4..15 of the word; 16: the whole word [pp.61-68]
    ranges_v: tuple[float, ...]  # +- full scale (V) by the slist range code (bits 8-11)
    srate_min: tuple[int, ...] | int  # by enabled analog channel count (DI-1100) or one value [p.48]
    dec_max: int  # 1: no ``dec`` command [p.48, "dec support"]
    deca: bool  # the ``deca`` multiplier is sent [p.48, p.52]
    digital_io: bool  # endo / dout / din [p.57, "Digital I/O Commands"]
    slist_max: int  # scan-list positions
    stream_digital: str  # "position0": D1 D0 in the LSBs of position 0 [p.61]; "word": slist 0x0008 [p.63, p.67]
    dividend: float = 60_000_000.0  # [p.48]
    digital_lines: int = 7  # D0..D6 [p.57]

    @property
    def range_v(self) -> float:
        return self.ranges_v[0]

    def srate_lo(self, n_analog: int) -> int:
        if isinstance(self.srate_min, tuple):
            return self.srate_min[max(1, min(n_analog, len(self.srate_min))) - 1]
        return self.srate_min

    def rate_bounds(self, n_analog: int) -> tuple[float, float]:
        """(lowest, highest) scan rate (Hz per channel) the model can run at with n_analog channels."""
        slowest = self.dividend / (SRATE_MAX * self.dec_max)
        return slowest, self.dividend / self.srate_lo(n_analog)

    def volts(self, counts, range_code: int = 0):
        """ADC counts -> volts: volts = full scale x counts / 2^(bits-1) [p.61, p.64, p.68]."""
        return np.asarray(counts, dtype=float) * (self.ranges_v[range_code] / (1 << (self.adc_bits - 1)))

    def counts(self, volts, range_code: int = 0) -> np.ndarray:
        """Volts -> the ADC counts the instrument reports (rounded, clipped to the converter's codes)."""
        half = 1 << (self.adc_bits - 1)
        c = np.rint(np.asarray(volts, dtype=float) / self.ranges_v[range_code] * half)
        return np.clip(np.nan_to_num(c), -half, half - 1).astype(np.int32)


MODELS: dict[str, ModelSpec] = {
    # DI-1100: 4 x 12-bit +-10 V; srate min 1500/2000/2500/3000 for 1..4 analog channels; no dec [p.48];
    # no digital I/O commands (p.57 leaves 1100 blank); D0 D1 ride in position 0's LSBs [p.61]
    "DI-1100": ModelSpec("DI-1100", "1100", 0x1101, 4, 12, (10.0,), (1500, 2000, 2500, 3000), 1, False, False, 4,
                         "position0"),
    # DI-1110: 8 x 12-bit +-10 V, srate min 375, no dec [p.48]; digital I/O [p.57]; slist as the DI-2108 [p.44]
    "DI-1110": ModelSpec("DI-1110", "1110", 0x1111, 8, 12, (10.0,), 375, 1, False, True, 11, "word"),
    # DI-2108: 8 x 16-bit +-10 V, srate min 375, dec 1..512 [p.48]. deca: the srate table lists 1..40000 for
    # the DI-2108 but its footnote *** says "Model DI-2008 and DI-2108 do not support the deca command":
    # velab never sends deca to a DI-2108 (lowest rate 60 MHz / (65535 x 512) = 1.79 Hz is low enough).
    "DI-2108": ModelSpec("DI-2108", "2108", 0x2107, 8, 16, (10.0,), 375, 512, False, True, 11, "word"),
}
MODEL_BY_NUMBER = {m.number: m for m in MODELS.values()}
MODEL_BY_PID = {m.pid_cdc: m for m in MODELS.values()}


def model(name: str) -> ModelSpec:
    """The ModelSpec of "DI-2108" / "2108" / "di2108"; ValueError naming the supported models."""
    key = str(name).upper().replace("_", "-").strip()
    if not key.startswith("DI-"):
        key = "DI-" + key.removeprefix("DI")
    if key not in MODELS:
        raise ValueError(f"unsupported DATAQ model {name!r} (supported: {', '.join(MODELS)})")
    return MODELS[key]


# ---------------------------------------------------------------- commands


def command(name: str, *args) -> bytes:
    """One command line: words joined by a space, decimal arguments, CR at the end [p.16]."""
    words = [name, *(str(int(a)) if not isinstance(a, str) else a for a in args)]
    return (" ".join(words)).encode("ascii") + CR


def info(n: int) -> bytes:
    """info 0: "DATAQ"; 1: model number; 2: firmware (hex); 6: serial number; 9: srate dividend [p.20]."""
    return command("info", n)


def stop() -> bytes:
    return command("stop")


def start() -> bytes:
    """``start 0``: begin scanning; never echoes [p.49, "start Command"]."""
    return command("start", 0)


def encode(mode: int = ENCODE_BINARY) -> bytes:
    return command("encode", mode)


def ps(code: int) -> bytes:
    """Packet size 16 x 2^code bytes, code 0..7 [p.20]."""
    if not 0 <= code < len(PACKET_SIZES):
        raise ValueError(f"ps code must be 0..7, got {code}")
    return command("ps", code)


def slist(position: int, value: int) -> bytes:
    """``slist offset config``: scan-list position (0..10) and its 16-bit word [p.39]."""
    if not 0 <= position <= 10 or not 0 <= value <= 0xFFFF:
        raise ValueError(f"slist {position} {value}: position 0..10, value 0..65535")
    return command("slist", position, value)


def srate(divisor: int) -> bytes:
    return command("srate", divisor)


def dec(factor: int) -> bytes:
    return command("dec", factor)


def deca(factor: int) -> bytes:
    return command("deca", factor)


def endo(mask: int) -> bytes:
    """Bit n = 1: port Dn is a switch (output); 0: an input. Re-initialises every port [p.57]."""
    if not 0 <= mask <= 0x7F:
        raise ValueError(f"endo mask must be 0..127, got {mask}")
    return command("endo", mask)


def dout(mask: int) -> bytes:
    """The 7-bit output state, bit n = Dn [p.58, "dout command"]."""
    if not 0 <= mask <= 0x7F:
        raise ValueError(f"dout value must be 0..127, got {mask}")
    return command("dout", mask)


def din() -> bytes:
    """Reply ``din N``: the state of all seven ports, bit n = Dn [p.58, "din command"]."""
    return command("din")


def packet_code(bytes_per_s: float, packets_per_s: float = 100.0) -> int:
    """The largest ps code whose packets still go out at least ``packets_per_s`` times a second: a packet is
    sent only when full, so small packets keep latency low, large ones avoid overflow at speed [p.21]."""
    code = 0
    for i, size in enumerate(PACKET_SIZES):
        if bytes_per_s / size >= packets_per_s:
            code = i
    return code


# ---------------------------------------------------------------- replies


class ReplyError(ValueError):
    """A reply line that does not echo the command sent (the driver names it as a device error)."""


def reply_text(sent: bytes, line: bytes) -> str:
    """The response part of a reply line (CR stripped): ``b"info 1\\r"``, ``b"info 1 2108"`` -> ``"2108"``;
    a plain echo -> ``""``. NUL and LF around a line are tolerated (the vendor's examples strip them).
    ReplyError if the line is not the command's echo."""
    cmd = sent.rstrip(CR).decode("ascii")
    text = line.strip(b"\r\n\x00").decode("ascii", "replace")
    if text == cmd:
        return ""
    if text.startswith(cmd + " "):
        return text[len(cmd) + 1:]
    raise ReplyError(f"{cmd!r} -> {text!r} (not its echo)")


def firmware_text(reply: str) -> str:
    """``info 2`` reply -> "1.01": the revision as hex digits (0x65 = 101 -> 1.01) [p.20, "info 2"]."""
    try:
        v = int(reply.strip(), 16)
    except ValueError:
        return reply.strip()
    return f"{v // 100}.{v % 100:02d}"


def firmware_code(version: str) -> str:
    """"1.01" -> "65": what a device of that firmware answers to ``info 2`` (the inverse of firmware_text)."""
    major, _, minor = version.partition(".")
    return format(int(major) * 100 + int(minor or 0), "X")


# ---------------------------------------------------------------- sample rate


@dataclass(frozen=True)
class RatePlan:
    srate: int
    dec: int
    deca: int
    rate_hz: float  # per channel: dividend / (srate x dec x deca) [p.48]


def rate_plan(spec: ModelSpec, rate_hz: float, n_analog: int) -> RatePlan:
    """The divisors for a per-channel scan rate and the exact rate they give [p.48, "srate Scan rate Command"].

    The smallest ``dec`` that brings srate within its bounds (dec = 1 whenever possible: no oversampling);
    ValueError naming the model's bounds if the rate cannot be reached."""
    lo, hi = spec.rate_bounds(n_analog)
    if not (lo * (1 - 1e-9) <= rate_hz <= hi * (1 + 1e-9)):
        raise ValueError(f"{spec.name}: rate {rate_hz:g} Hz with {n_analog} analog channel(s) is outside "
                         f"{lo:.4g}..{hi:.6g} Hz")
    s_lo = spec.srate_lo(n_analog)
    for d in range(1, spec.dec_max + 1):
        s = int(round(spec.dividend / (rate_hz * d)))
        if s <= SRATE_MAX:
            s = max(s, s_lo)
            return RatePlan(s, d, 1, spec.dividend / (s * d))
    raise ValueError(f"{spec.name}: rate {rate_hz:g} Hz cannot be reached")  # unreachable after the bounds check


# ---------------------------------------------------------------- binary stream


def encode_words(spec: ModelSpec, counts: np.ndarray, digital: np.ndarray | None = None) -> np.ndarray:
    """(n, k) analog counts -> (n, k) 16-bit stream words (the device side, for the simulator).

    12-bit models: counts in bits 4..15 [p.61, p.63]; the DI-1100 puts D1 D0 in bits 1, 0 of position 0 [p.61]."""
    c = np.asarray(counts, dtype=np.int32)
    w = (c << 4) & 0xFFFF if spec.adc_bits == 12 else c & 0xFFFF
    if spec.stream_digital == "position0" and digital is not None and w.shape[1]:
        w[:, 0] |= np.asarray(digital, dtype=np.int32) & 0x3
    return w.astype(np.uint16)


def digital_word(state: np.ndarray | int) -> np.ndarray:
    """The digital-input word: low byte ~D1 ~D0 in bits 1, 0; high byte D6..D0 [p.63, p.67]."""
    s = np.asarray(state, dtype=np.int32) & 0x7F
    return ((~s & 0x3) | (s << 8)).astype(np.uint16)


def digital_state(words: np.ndarray) -> np.ndarray:
    """D6..D0 from digital-input words (the high byte) [p.67]."""
    return (np.asarray(words, dtype=np.uint16) >> 8) & 0x7F


def digital_word_valid(words: np.ndarray) -> np.ndarray:
    """A digital-input word as the document lays it out: low byte bits 7..2 zero, high byte bit 7 zero, and
    bits 1, 0 of the low byte the complements of D1, D0 [p.67]. Any other word means the framing is lost."""
    w = np.asarray(words, dtype=np.uint16)
    lo, hi = w & 0xFF, w >> 8
    return ((lo & 0xFC) == 0) & ((hi & 0x80) == 0) & ((lo & 0x3) == (~hi & 0x3))


@dataclass(frozen=True)
class ScanLayout:
    """What one scan (a pass through the scan list) holds: the analog inputs in order, the digital word's
    position (or None), and the byte checks that tell a scan in frame from one that is not."""

    spec: ModelSpec
    analog: tuple[int, ...]  # analog input of each analog position, in scan-list order
    digital_pos: int | None = None  # scan-list position of the digital-input word (SLIST_DIGITAL_IN)

    @property
    def positions(self) -> int:
        return len(self.analog) + (self.digital_pos is not None)

    @property
    def scan_bytes(self) -> int:
        return 2 * self.positions

    def slist_words(self) -> list[int]:
        words = list(self.analog)  # analog word = input number, range code 0 (+-10 V) [p.40, p.44]
        if self.digital_pos is not None:
            words.insert(self.digital_pos, SLIST_DIGITAL_IN)
        return words

    def analog_positions(self) -> list[int]:
        return [p for p in range(self.positions) if p != self.digital_pos]

    def decode(self, data: bytes) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """Whole scans -> (counts (n, k) int16, digital state (n,) or None, in_frame (n,) bool).

        ``in_frame`` is False for a scan whose bytes break the document's layout: a 12-bit model's analog
        word with bits 0..3 set (bits 2..3 on the DI-1100's position 0, whose bits 1..0 are D1 D0) [p.61,
        p.63]; a digital word not laid out as digital_word_valid says. A 16-bit model with no digital word
        in its scan list has no such check (every word is a valid count)."""
        n = len(data) // self.scan_bytes
        words = np.frombuffer(data[: n * self.scan_bytes], dtype="<u2").reshape(n, self.positions)
        ap = self.analog_positions()
        aw = words[:, ap]
        ok = np.ones(n, dtype=bool)
        dig = None
        if self.spec.adc_bits == 12:
            counts = (aw.astype(np.int16) >> 4).astype(np.int16)
            spare = np.full(len(ap), 0xF, dtype=np.uint16)
            if self.spec.stream_digital == "position0" and ap and ap[0] == 0:
                spare[0] = 0xC
                dig = (aw[:, 0] & 0x3).astype(np.int64)
            ok &= ~((aw & spare) != 0).any(axis=1)
        else:
            counts = aw.astype(np.int16)
        if self.digital_pos is not None:
            dw = words[:, self.digital_pos]
            ok &= digital_word_valid(dw)
            dig = digital_state(dw).astype(np.int64)
        return counts, dig, ok

    @property
    def checked(self) -> bool:
        """True if a scan out of frame can be told from one in frame (see decode)."""
        return self.spec.adc_bits == 12 or self.digital_pos is not None


def scan_layout(spec: ModelSpec, analog: list[int] | tuple[int, ...], with_digital: bool = True) -> ScanLayout:
    """The scan list for these analog inputs; on models with a digital-input word it goes last (so a byte lost
    anywhere in a scan shifts that scan's own digital word: seen at once) [p.39: any order is allowed]."""
    analog = tuple(int(a) for a in analog)
    if not analog:
        raise ValueError("scan at least one analog input")
    if len(set(analog)) != len(analog):
        raise ValueError(f"an input may appear in the scan list only once [slist, p.40]: {analog}")
    bad = [a for a in analog if not 0 <= a < spec.analog_inputs]
    if bad:
        raise ValueError(f"{spec.name} has analog inputs 0..{spec.analog_inputs - 1}, not {bad[0]}")
    dpos = len(analog) if (with_digital and spec.stream_digital == "word") else None
    lay = ScanLayout(spec, analog, dpos)
    if lay.positions > spec.slist_max:
        raise ValueError(f"{spec.name}: {lay.positions} scan-list positions, at most {spec.slist_max}")
    return lay


@dataclass(frozen=True)
class Chunk:
    """Consecutive in-frame scans. ``lost_before``: scans estimated lost just before them (framing was lost and
    found again: bytes skipped / scan size, rounded up; the stream has no counter to make it exact)."""

    counts: np.ndarray  # (n, k) int16 in scan-list order of the analog positions
    digital: np.ndarray | None  # (n,) D6..D0 (DI-1100: D1 D0), or None
    lost_before: int = 0
    skipped_bytes: int = 0


class StreamDecoder:
    """Binary stream bytes -> Chunks of whole, in-frame scans. Pure (no I/O, no clock).

    The stream is two bytes per scan-list position, in order, with nothing in between [p.60]: alignment is
    kept by counting. Where the layout can be checked (ScanLayout.decode), a scan out of frame (a byte lost or
    junk inserted on the way) starts a hunt: byte by byte until ``confirm`` consecutive scans are in frame;
    the bytes skipped (and the first scan of the lock, which may
    straddle the junk) are counted. A trailing ``stop 01`` (the overflow report, p.50) is held back, not decoded
    (``overflow_pending``)."""

    CHECK_BITS = 24  # a hunt locks only after this many layout bits agreed (false lock ~ 2^-24)

    def __init__(self, layout: ScanLayout):
        self.layout = layout
        self.buf = bytearray()
        self.hunting = False
        self.skipped = 0  # bytes skipped in the current hunt
        self.resyncs = 0
        self.skipped_total = 0
        self.scans = 0
        spec = layout.spec
        bits = 0
        if spec.adc_bits == 12:
            bits += 4 * len(layout.analog) - (2 if spec.stream_digital == "position0" else 0)
        if layout.digital_pos is not None:
            bits += 3  # shifted by a byte, an idle word (D2..D6 low) keeps its zero bits: 3 bits are checked
        self.confirm = max(2, -(-self.CHECK_BITS // bits)) if bits else 0

    @property
    def overflow_pending(self) -> bool:
        return self.buf.endswith(OVERFLOW_REPORT)

    def feed(self, data: bytes) -> list[Chunk]:
        self.buf += data
        lay, sb = self.layout, self.layout.scan_bytes
        out: list[Chunk] = []
        pos = 0
        end = len(self.buf) - (len(OVERFLOW_REPORT) if self.overflow_pending else 0)
        while True:
            if self.hunting:
                need = self.confirm * sb
                while end - pos >= need:
                    _, _, ok = lay.decode(bytes(self.buf[pos:pos + need]))
                    if ok.all():
                        break
                    pos += 1
                    self.skipped += 1
                else:
                    break  # more bytes needed to decide
                # the first scan of the lock may begin inside the junk and still pass (only its checked bits are
                # real): it is skipped too; the next ones are whole scans
                pos += sb
                self.skipped += sb
                self.hunting = False
                self.resyncs += 1
                self.skipped_total += self.skipped
            n = (end - pos) // sb
            if n <= self.confirm:
                break  # the last ``confirm`` scans wait for the ones after them (see below)
            counts, dig, ok = lay.decode(bytes(self.buf[pos:pos + n * sb]))
            k = n if ok.all() else int(np.argmin(ok))
            # a scan out of frame can pass its checks by chance (a lost byte in a high byte shifts only what
            # follows; an idle digital word leaves few bits to check): a scan is delivered only once ``confirm``
            # scans after it are in frame; those before an out-of-frame scan are thrown away
            good = max(0, k - self.confirm)
            if good:
                lost = -(-self.skipped // sb)
                out.append(Chunk(counts[:good], None if dig is None else dig[:good], lost, self.skipped))
                self.skipped = 0
                self.scans += good
                pos += good * sb
            if k == n:
                break
            doubtful = k - good  # scans in frame but not confirmed, before the out-of-frame scan k
            pos += doubtful * sb + 1  # hunt from scan k's second byte
            self.skipped += doubtful * sb + 1
            self.hunting = True
        del self.buf[:pos]
        return out

    def flush(self) -> list[Chunk]:
        """The scans still waiting at the end of a stream: those in frame, up to the first that is not."""
        sb = self.layout.scan_bytes
        n = len(self.buf) // sb
        if self.hunting or not n:
            return []
        counts, dig, ok = self.layout.decode(bytes(self.buf[:n * sb]))
        k = n if ok.all() else int(np.argmin(ok))
        del self.buf[:n * sb]
        if not k:
            return []
        self.scans += k
        return [Chunk(counts[:k], None if dig is None else dig[:k], -(-self.skipped // sb), self.skipped)]

    def tail(self) -> bytes:
        """The bytes not decoded yet (a partial scan, a held-back report)."""
        return bytes(self.buf)
