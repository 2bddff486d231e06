"""The run's time line: pressure blocks -> time axis, gaps, quality, baseline, trigger, fit window.

Fed by the pressure source's thread (``process(block, codes)``: the driver's per-sample quality codes
by channel); hands writes to the writer stage and reports through the hooks. Every transducer of the
rig is recorded (its head, pressure, raw counts and quality: velab.recording.transducers); the
steady head, the ceiling, the trigger and the fit window are the valve's transducer's, and a
flagged sample of any transducer shortens the window every section is fitted on. Every boundary is counted in samples of the
pressure source's clock, so a fast simulated clock makes a whole run fast, and one rule decides
each boundary: a span [a, b) on the run's axis is in when the next sample's time reaches
``b - 0.5/fs`` (the fit window and the record's end use the same test, so a fit window equal to
the duration always closes before the run ends).
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np

from velab.drivers.blocks import QUALITY_CODE, QUALITY_CODES
from velab.drivers.base import Quality
from velab.fitting.window import BASELINE_S, steady_head, window_slice
from velab.recording.online_fit import MIN_FIT_WINDOW_S
from velab.recording.ops import Append, Gap, Trigger
from velab.recording.safety import OK, ceiling_crossing, describe_codes, finite_max
from velab.recording.transducers import TransducerChannel
from velab.valvelaw import commanded_time_s

# samples kept from before the trigger is marked: the fit path's baseline (velab.fitting.window), and
# 1 s for the trigger's estimate being ahead of the last sample processed when it was marked
PRE_TRIGGER_KEPT_S = BASELINE_S + 1.0


# the stroke is measured from the feedback samples whose opening (the part of the stroke still to go, %)
# lies in this band, at least this many of them; past the band's lower end the stroke is taken as seen
STROKE_BAND_PCT = (10.0, 90.0)
HOST_LAG_S = 0.1  # host seconds by which the trigger's latest start may be late (a descheduled acquisition thread)
MIN_STROKE_SAMPLES = 3


def stroke_opening_pct(pos_pct, end_pct: float) -> np.ndarray:
    """The valve position as the opening of the commanded stroke: 100 % open, 0 % at its end position."""
    return (np.asarray(pos_pct, dtype=float) - end_pct) / (100.0 - end_pct) * 100.0


def trigger_from_position(t: np.ndarray, pos_pct: np.ndarray, beta: float, gamma: float, end_pct: float) -> float | None:
    """The trigger instant from the measured valve opening (the commanded sigmoid, only t0 unknown).

    opening = end + (100 - end) / (1 + exp(beta (t - t0) + gamma)): from every sample
    between 10 % and 90 % of the stroke, t0 = t - (ln(100/p - 1) - gamma) / beta; median.
    """
    lo, hi = STROKE_BAND_PCT
    p = stroke_opening_pct(pos_pct, end_pct)
    sel = np.isfinite(p) & (p > lo) & (p < hi)
    if sel.sum() < MIN_STROKE_SAMPLES:
        return None
    return float(np.median(np.asarray(t, dtype=float)[sel] - commanded_time_s(p[sel], beta, gamma)))


def slice_block(b, k: int, host_rate_hz: float):
    """The block's first ``k`` samples; its samples ``host_rate_hz`` apart in host time (``Block.host_times_at``)."""
    sq = None if b.sample_quality is None else b.sample_quality[:k]
    return replace(b, raw=b.raw[:k], signal=b.signal[:k], values=b.values[:k], sample_quality=sq,
                   host_time_s=b.host_time_s - (b.n - k) / host_rate_hz)


QUICK_FRACTIONS = (0.25, 0.5, 0.75)  # intermediate quick fits at these fractions of the fit window
T, HEAD, POSITION = 0, 1, 2  # rows of the window's buffer; the other transducers' heads follow


@dataclass(frozen=True)
class FitRecord:
    """The record the fit path takes (``Timeline.fit_window``): the run's axis from a few seconds before the
    trigger to the end of the clean part of the window, the valve transducer's absolute head there, the
    other transducers' by name (a rig with several sections), the valve position (or None)."""

    t: np.ndarray
    head: np.ndarray
    trigger_time_s: float
    window_s: float
    note: str = ""
    position: np.ndarray | None = None
    section_heads: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Counters:
    """The time line's counters at one instant (``Timeline.counters()``: read under its lock)."""

    now_axis: float
    baseline_s: float
    baseline_complete: bool
    n_written: int
    lost: int
    gaps: int
    flagged: int
    peak: float
    trigger_time: float | None
    trigger_from_feedback: bool
    window_closed: bool


class Timeline:
    """State of one run's samples. Only the acquisition thread calls ``process``; other threads read
    its state through ``counters()`` and the properties, and mark the trigger, all under its lock
    (re-entrant: a hook called from ``process`` may read the counters again)."""

    def __init__(self, settings, fs: float, manoeuvre: tuple[float, float, float], ceiling_m: float,
                 pressure_channel: str, valve_channel: str | None, hooks, write, on_window_closed,
                 on_baseline=lambda: None,
                 others: tuple[TransducerChannel, ...] = (), clock_scale: float = 1.0, now=time.monotonic):
        self.s = settings
        self.fs = fs
        self.beta, self.gamma, self.end_pct = manoeuvre
        self.ceiling = ceiling_m
        self.pch, self.vch = pressure_channel, valve_channel
        self.others = tuple(others)  # the rig's transducers other than the valve's (velab.recording.transducers)
        self.hooks = hooks
        self.write = write  # write(velab.recording.ops message) -> the writer stage
        self.on_window_closed = on_window_closed
        self.on_baseline = on_baseline  # wakes the control thread: a queued trigger goes out at once
        # quick fits at these instants after the trigger
        self._quick_windows = [f * settings.fit_window_s for f in QUICK_FRACTIONS]
        self.n_pre = int(round(settings.pretrigger_s * fs))
        self.gidx = 0  # global index of the next sample (gaps included)
        self.n_written = 0
        self.lost = 0
        self.gaps = 0
        self.flagged = 0
        self.peak = -math.inf
        self.trigger_idx: int | None = None
        self.trigger_time: float | None = None
        self.trigger_measured = False  # the feedback was looked at (whether or not a stroke was seen)
        self.trigger_from_feedback = False  # ... and the instant measured from it
        # the latest axis instant the stroke can have started (the command's reply came back then); None: the
        # command is still out, so it can start any time (velab.recording.run.fire_trigger, commit_trigger)
        self.trigger_latest: float | None = None
        self._pos_t: list = []
        self._pos_v: list = []
        self._stroke_passed = False  # the feedback was seen past the stroke band (closed beyond its 10 %)
        self._fit = None  # the window's rows: axis, head, valve position, the other transducers' heads
        self._fit_n = 0
        self._pre_blocks: deque = deque()  # (axis time, head, others' heads) blocks before the trigger was marked
        self.clean_until: float | None = None  # first flagged / lost instant after the trigger
        self.window_closed = False
        self.ended = False  # no more samples are taken (end requested)
        self._quick_next = 0
        self._seen_quality: set = set()
        # the device's sample index at host time h is at least ``_lead + h x rate``: each block's last
        # index less its arrival (here, ``now()``) times the device's samples per host second; the
        # largest over the blocks is the block that waited least (velab.recording.run marks the
        # trigger with it). rate: fs x clock_scale (a simulated rig's fast clock; 1 at a real bench)
        self._rate = fs * clock_scale
        self._now = now
        self._lead: float | None = None
        self._lock = threading.RLock()

    # ---------------------------------------------------------------- counters (any thread)
    @property
    def now_axis(self) -> float:
        with self._lock:
            return (self.gidx - self.n_pre) / self.fs

    @property
    def device_axis(self) -> float:
        """The axis time of the sample the device is making now (``_index_now``: the block that waited least,
        plus the samples made since; never before the samples processed): what a slow channel's reading taken
        now is stamped with, right through a stall of the samples' processing."""
        with self._lock:
            return (self._index_now() - self.n_pre) / self.fs

    @property
    def baseline_s(self) -> float:
        with self._lock:
            return self.gidx / self.fs

    @property
    def triggered(self) -> bool:
        """The trigger is marked (the command is going out or went out)."""
        with self._lock:
            return self.trigger_idx is not None

    def counters(self) -> Counters:
        with self._lock:
            return Counters(now_axis=(self.gidx - self.n_pre) / self.fs, baseline_s=self.gidx / self.fs,
                            baseline_complete=self.gidx >= self.n_pre, n_written=self.n_written, lost=self.lost,
                            gaps=self.gaps, flagged=self.flagged, peak=self.peak, trigger_time=self.trigger_time,
                            trigger_from_feedback=self.trigger_from_feedback, window_closed=self.window_closed)

    def steady_head(self, fallback: float | None) -> float | None:
        """The fit path's steady head (velab.fitting.window) of the baseline recorded so far: before
        the trigger, or before now if it is not marked yet; ``fallback`` if there is none."""
        with self._lock:
            t, h = self._record()
            trigger = self.trigger_time if self.trigger_time is not None else self.now_axis
        value = steady_head(t, h, trigger, math.nan, self.fs)
        return value if math.isfinite(value) else fallback

    def _record(self) -> tuple[np.ndarray, np.ndarray]:
        """(axis, head) kept: the baseline's blocks, then the window's samples so far (a copy)."""
        n = self._fit_n
        ts = [b[0] for b in self._pre_blocks] + ([self._fit[T, :n]] if n else [])
        hs = [b[1] for b in self._pre_blocks] + ([self._fit[HEAD, :n]] if n else [])
        return (np.concatenate(ts), np.concatenate(hs)) if ts else (np.empty(0), np.empty(0))

    # ---------------------------------------------------------------- the trigger (control thread)
    def mark_trigger(self) -> float:
        """The trigger command is being sent now: estimate its instant on the sample clock.

        The samples processed so far lag the device by whatever is still queued (a loaded host: seconds
        of the fast clock's axis): the estimate is the device's index now, from the block that
        waited least (``_index_now``), never before the samples already processed."""
        with self._lock:
            idx = self._index_now()
            lag_s = (idx - self.gidx) / self.fs
            cap = int((self.s.fit_window_s + 2.0) * self.fs + (idx - self.gidx)) + 1
            self._fit = np.empty((3 + len(self.others), cap))
            self._fit_n = 0
            self.trigger_idx = idx
            self.trigger_time = (idx - self.n_pre) / self.fs
        if lag_s >= 1.0:  # said, so a record whose trigger is estimated far ahead of its data is explained
            self.hooks.log("trigger", f"the pressure stream lags the device by about {lag_s:.2f} s of samples "
                                      "at the trigger command")
        return self.trigger_time

    def _index_now(self) -> int:
        """The device's sample index now: the tightest lower bound the blocks give (each one's index
        when it arrived, plus the samples made since), at least the next sample to process."""
        if self._lead is None:
            return self.gidx
        return max(self.gidx, int(round(self._lead + self._now() * self._rate)))

    def commit_trigger(self) -> bool:
        """The trigger command was carried out (its reply, or read-back, came now): its estimate goes into
        the file, unless the valve feedback has measured the instant already (the command's reply was lost
        and read back). The stroke started by now: the feedback is watched until a fit window after it
        before "no stroke seen"."""
        with self._lock:
            self.trigger_latest = max(self.trigger_time, (self._index_now() - self.n_pre) / self.fs)
            if self.trigger_from_feedback:
                return False
            self.write(Trigger(self.trigger_time))
            return True

    def _measure_trigger(self) -> None:
        self.trigger_measured = True
        if not self._pos_t:
            t0 = None
        else:
            t0 = trigger_from_position(np.concatenate(self._pos_t), np.concatenate(self._pos_v), self.beta,
                                       self.gamma, self.end_pct)
        if t0 is None:
            if self._stroke_passed:
                # the valve did close: the feedback is neither stuck nor disconnected, its samples over the stroke
                # are missing (lost, or a rate too low for the stroke)
                what = (f"the stroke passed its {STROKE_BAND_PCT[0]:g}-{STROKE_BAND_PCT[1]:g} % band with "
                        f"{self._in_band_samples()} sample(s) inside it (at least {MIN_STROKE_SAMPLES} time it: "
                        f"samples lost over the stroke?)")
            else:
                what = "no stroke seen (stuck or disconnected feedback)"
            self.hooks.fault("valve", f"valve-position feedback: {what}; the trigger instant is the command's estimate",
                             "quality", channel=self.vch)
            return
        estimate = self.trigger_time
        self.trigger_time = t0
        self.trigger_from_feedback = True
        self.write(Trigger(t0))
        self.hooks.log("trigger", f"trigger instant measured from the valve position: t = {t0:.5f} s")
        self.hooks.emit("trigger", {"trigger_time_s": t0, "measured": True, "estimate_s": estimate})

    def finish(self) -> None:
        """At the end of the run: measure the trigger if the stroke was seen but not yet used. A run ended
        (stopped, aborted) before its samples could show the stroke keeps the command's estimate and says so:
        that is not a feedback fault."""
        with self._lock:
            self.ended = True
            if self.trigger_time is None or self.trigger_measured or not self.vch:
                return
            # the latest start is a lower bound of the device's index when the TRIGGER's reply came (the blocks
            # still queued lag it): a record ending within a host hiccup (HOST_LAG_S of device time at this clock)
            # after that start plus the stroke can hold none of it, which says nothing of the feedback
            lag = HOST_LAG_S * self._rate / self.fs
            if self._in_band_samples() >= MIN_STROKE_SAMPLES or \
                    self._reached(self._stroke_by() + self._stroke_s() + lag):
                self._measure_trigger()
            else:
                self.hooks.log("trigger", "the record ended before the valve's stroke was in its samples: the "
                                          "trigger instant is the command's estimate")

    def _in_band_samples(self) -> int:
        """The feedback's samples kept inside the stroke band so far (what the trigger is measured from)."""
        return sum(p.size for p in self._pos_t)

    def _stroke_s(self) -> float:
        """From the stroke's start (t0) until the commanded opening passes the band's lower end (10 %: 90 % of
        the stroke done), when the feedback shows the stroke (``_after_trigger``'s ``passed``)."""
        return max(0.0, float(commanded_time_s(STROKE_BAND_PCT[0], self.beta, self.gamma)))

    # ---------------------------------------------------------------- blocks (acquisition thread)
    def process(self, b, codes: dict) -> None:
        """One block and the driver's per-sample quality codes of its channels (by channel name)."""
        with self._lock:
            if not self.ended:
                self._process(b, codes)

    def _process(self, b, codes: dict) -> None:
        s, fs = self.s, self.fs
        p_codes, v_codes = codes[self.pch], codes.get(self.vch) if self.vch else None
        o_codes = [codes[o.adc_channel] for o in self.others]
        if b.lost_before or b.restarted:  # a restarted device is never taken as contiguous, even with 0 lost
            self._gap(int(b.lost_before), bool(b.restarted))
            if b.restarted:  # its lost count is estimated: the blocks before say nothing of its index now
                self._lead = None
        n = b.n
        g = self.gidx + np.arange(n)
        t = (g - self.n_pre) / fs
        if self.trigger_time is not None:
            keep = t < self._stroke_by() + s.duration_s - 0.5 / fs
            if not keep.all():
                n = int(keep.sum())
                b, g, t = slice_block(b, n, self._rate), g[:n], t[:n]
                p_codes = p_codes[:n]
                v_codes = None if v_codes is None else v_codes[:n]
                o_codes = [c[:n] for c in o_codes]
        if n == 0:
            self._check_boundaries()
            return
        head = b.head_m(self.pch)
        pi = b.channels.index(self.pch)
        has_v = bool(self.vch) and self.vch in b.channels
        pos = b.column(self.vch) if has_v else np.full(n, np.nan)
        pos_raw = b.raw_column(self.vch).astype(np.int32) if has_v else np.zeros(n, np.int32)
        vq = v_codes if v_codes is not None else np.zeros(n, np.uint8)
        channels = {
            "head": head, "valve_position": pos, "pressure": b.values[:, pi], "pressure_raw": b.raw[:, pi].astype(np.int32),
            "valve_position_raw": pos_raw, "sample_index": g, "host_time": b.host_times_at(self._rate),
            "pressure_quality": p_codes, "valve_position_quality": vq,
        }
        o_heads = []
        for o, oc in zip(self.others, o_codes):
            j = b.channels.index(o.adc_channel)
            o_heads.append(b.head_m(o.adc_channel))
            channels |= {o.channel("head"): o_heads[-1], o.channel("pressure"): b.values[:, j],
                         o.channel("pressure_raw"): b.raw[:, j].astype(np.int32), o.channel("pressure_quality"): oc}
        self.write(Append(t, channels))
        self.n_written += n
        before = self.gidx
        self.gidx += n
        lead = (self.gidx - 1) - self._now() * self._rate
        self._lead = lead if self._lead is None else max(self._lead, lead)
        if before < self.n_pre <= self.gidx:
            self.on_baseline()
        ok = p_codes == OK
        every_ok = ok.copy()
        for oc in o_codes:
            every_ok &= oc == OK
        self.flagged += int(n - every_ok.sum())  # samples with a flagged transducer
        self.peak = max(self.peak, finite_max(np.where(ok, head, np.nan)))
        self._quality(p_codes, "pressure", self.pch, t)
        for o, oc in zip(self.others, o_codes):
            self._quality(oc, "pressure", o.adc_channel, t, transducer=o.name)
        if has_v:
            self._quality(vq, "valve", self.vch, t)
        if self.trigger_idx is not None:
            self._after_trigger(t, head, pos, o_heads)
        else:
            self._keep_pre(t, head, o_heads)
        self.hooks.emit("samples", {"time_s": t, "head_m": head, "valve_position": pos, "lost": int(b.lost_before),
                                    "quality": p_codes})
        i = ceiling_crossing(head, p_codes, self.ceiling)
        if i is not None:
            self.hooks.request_end("aborted", f"pressure ceiling: head {head[i]:.2f} m > {self.ceiling:.2f} m "
                                              f"at t = {t[i]:.3f} s")
        self._check_boundaries()

    def _gap(self, lost: int, restarted: bool) -> None:
        self.write(Gap(self.n_written, lost))
        self.lost += lost
        self.gaps += 1
        self.gidx += lost
        what = "estimated (reconnection or restart)" if restarted else "exact"
        note = f"{lost} samples lost before sample {self.gidx} ({what})"
        if restarted:
            note = "pressure ADC reconnected; " + note
        self.hooks.fault("pressure", note, "samples_lost", lost=lost, restarted=restarted)
        if self.trigger_idx is not None and not self.window_closed and self.clean_until is None:
            self.clean_until = (self.gidx - lost - self.n_pre) / self.fs

    def _quality(self, codes, role: str, channel: str, t, transducer: str | None = None) -> None:
        """Each code once per channel (a fault event, so the run is flagged); a flagged transducer sample
        after the trigger ends the clean window; a transducer flagged before it ends the run.
        ``transducer``: the rig's name of a transducer other than the valve's (its channel is named too)."""
        bad = codes != OK
        if not bad.any():
            return
        first = int(np.flatnonzero(bad)[0])
        if role == "pressure" and self.trigger_idx is not None and not self.window_closed and self.clean_until is None:
            self.clean_until = float(t[first])
        fresh = [int(c) for c in np.unique(codes[bad]) if (role, channel, int(c)) not in self._seen_quality]
        if fresh:
            for c in fresh:
                self._seen_quality.add((role, channel, c))
            what = {QUALITY_CODE[Quality.STALE]: "stuck channel"}.get(fresh[0], QUALITY_CODES[fresh[0]].value)
            label = channel if transducer is None else f"{channel} (transducer {transducer})"
            extra = {} if transducer is None else {"transducer": transducer}
            self.hooks.fault(role, f"{label} samples flagged from t = {t[first]:.3f} s: {what} "
                                   f"({describe_codes(codes)} in this block)", "stuck" if what == "stuck channel"
                             else "quality", channel=channel, quality=QUALITY_CODES[fresh[0]].value, **extra)
            if role == "pressure" and self.trigger_idx is None:
                # blind before the trigger: never start a manoeuvre on a transducer that is not plausible
                who = "pressure transducer" if transducer is None else f"pressure transducer {transducer!r} ({channel})"
                self.hooks.request_end("aborted", f"{who} fault before the trigger ({what}): manoeuvre cancelled")

    def _after_trigger(self, t, head, pos, o_heads) -> None:
        s = self.s
        if not self.trigger_measured and self.vch:
            lo, hi = STROKE_BAND_PCT
            pn = stroke_opening_pct(pos, self.end_pct)
            with np.errstate(invalid="ignore"):
                sel = (pn > lo) & (pn < hi)
                passed = (pn < lo).any()
            if sel.any():
                self._pos_t.append(t[sel])
                self._pos_v.append(pos[sel])
            self._stroke_passed |= bool(passed)
            if passed and self._pos_t:
                self._measure_trigger()
        buf, n0 = self._fit, self._fit_n
        if n0 + t.size > buf.shape[1] and not self.window_closed:
            # sized from the trigger's estimate at the command: a measured trigger later than that (a late
            # command at the fast clock on a loaded host: seconds of axis) needs more; the window is kept whole
            grow = max(2 * buf.shape[1], n0 + t.size)  # (doubling: a copy now and then)
            buf = self._fit = np.concatenate([buf[:, :n0], np.empty((buf.shape[0], grow - n0))], axis=1)
        k = min(t.size, buf.shape[1] - n0)
        buf[T, n0:n0 + k] = t[:k]
        buf[HEAD, n0:n0 + k] = head[:k]
        buf[POSITION, n0:n0 + k] = pos[:k] if pos is not None else np.nan
        for i, h in enumerate(o_heads):
            buf[POSITION + 1 + i, n0:n0 + k] = h[:k]
        self._fit_n += k
        if not self.window_closed and self.trigger_measured and self.clean_until is None:
            after = float(t[-1]) - self.trigger_time
            quick = self._quick_windows
            if s.fit and s.online_fit and s.intermediate_fits and self._quick_next < len(quick) \
                    and after >= quick[self._quick_next]:
                self._quick_next += 1
                self.on_window_closed(quick[self._quick_next - 1], final=False)

    def _keep_pre(self, t, head, o_heads) -> None:
        pb = self._pre_blocks
        pb.append((t.copy(), np.array(head, dtype=float), tuple(np.array(h, dtype=float) for h in o_heads)))
        while len(pb) > 1 and pb[1][0][0] < float(t[-1]) - PRE_TRIGGER_KEPT_S:
            pb.popleft()

    def _reached(self, t_axis: float) -> bool:
        return self.now_axis >= t_axis - 0.5 / self.fs

    def _stroke_by(self) -> float:
        """The axis instant the run's trigger is taken at for its window and end: the trigger's (measured, or
        the estimate when there is no feedback or it was looked at); while the feedback is awaited, the latest
        instant the stroke can have started (inf while the command is out). A command that reached the
        actuator late (a loaded host; at the fast clock 0.1 s of host time is 1.2 s of the axis) starts a
        stroke after the estimate's window: it is measured, not "no stroke seen"."""
        if self.trigger_measured or not self.vch:
            return self.trigger_time
        return math.inf if self.trigger_latest is None else self.trigger_latest

    def _check_boundaries(self) -> None:
        if self.trigger_time is None:
            return
        if not self.trigger_measured and self.vch and self._reached(self._stroke_by() + self.s.fit_window_s):
            self._measure_trigger()
        # (the measured trigger may be later than the commanded one, the window then closes later)
        if not self.window_closed and (self.trigger_measured or not self.vch) \
                and self._reached(self.trigger_time + self.s.fit_window_s):
            self.window_closed = True
            self.hooks.emit("message", f"fit window closed ({self.s.fit_window_s:g} s after the trigger)")
            if self.s.fit and self.s.online_fit:
                self.on_window_closed(self.s.fit_window_s, final=True)
        if self._reached(self._stroke_by() + self.s.duration_s):
            self.hooks.request_end("completed", "")

    # ---------------------------------------------------------------- the fit's data
    def stroke_record(self) -> tuple[np.ndarray, np.ndarray, float] | None:
        """(time, valve position %, the run's trigger instant) after the trigger, for the measured stroke
        (velab.recording.stroke: gamma at the run file's trigger_time, as the file's manoeuvre); None without a
        position channel or a trigger."""
        with self._lock:
            if not self.vch or self.trigger_time is None or self._fit is None:
                return None
            n = self._fit_n
            return self._fit[T, :n].copy(), self._fit[POSITION, :n].copy(), float(self.trigger_time)

    def fit_window(self, window_s: float) -> FitRecord:
        """The record the fit path (velab.fitting.prepare) takes (:class:`FitRecord`), the same samples as
        in the run file, from a few seconds before the trigger to the end of the clean part of the window.

        Flagged (any transducer's) or lost samples inside the window shorten it to the clean part before
        them (if at least 2 s); otherwise ValueError says why there is no fit.
        """
        with self._lock:  # (the acquisition thread may be adding samples)
            note = ""
            if self.clean_until is not None:
                avail = self.clean_until - self.trigger_time
                if avail < window_s:
                    if avail < MIN_FIT_WINDOW_S:
                        raise ValueError(f"no fit: flagged or lost samples {max(avail, 0):.2f} s after the trigger, "
                                         f"inside the fit window (a clean window of at least "
                                         f"{MIN_FIT_WINDOW_S:g} s is needed)")
                    window_s = math.floor(avail * self.fs) / self.fs
                    note = f"fit window shortened to {window_s:.2f} s: flagged or lost samples after it"
            n, buf = self._fit_n, self._fit
            end = window_slice(buf[T, :n], self.trigger_time, window_s, self.fs).stop
            t = np.concatenate([b[0] for b in self._pre_blocks] + [buf[T, :end]])
            h = np.concatenate([b[1] for b in self._pre_blocks] + [buf[HEAD, :end]])
            others = {o.name: np.concatenate([b[2][i] for b in self._pre_blocks] + [buf[POSITION + 1 + i, :end]])
                      for i, o in enumerate(self.others)}
            pos = None
            if self.vch:  # the manoeuvre's input (velab.fitting.manoeuvre); open before the trigger
                pre = sum(b[0].size for b in self._pre_blocks)
                pos = np.concatenate([np.full(pre, 100.0), buf[POSITION, :end]])
            return FitRecord(t, h, float(self.trigger_time), window_s, note, pos, others)
