"""A recorded head record -> the calibration data (window, steady head, fit rate), and its calibration.

``prepare_record`` is the single place where a record becomes what the fitter calibrates on;
``velab fit``, the recorder's online fit and the GUI archive's re-fit all call it (through
velab.fitting.entry.fit_record), so an offline re-fit of a recorded run reproduces its online fit exactly:

1. steady head: mean of the baseline, the finite head samples of the last ``BASELINE_S`` before
   the trigger after the last non-finite one (the rig's steady head if none); velab.fitting.window
   states this rule and the window's for every caller (the recorder, the run-file reader);
2. window: samples with trigger - dt/2 <= t < trigger + window - dt/2, time from the trigger;
3. anti-alias decimation to the fit rate: q = the largest whole divisor of the record rate
   with record rate / q >= FIT_RATE_PER_BAND x the manoeuvre's band, zero-phase FIR (scipy.signal's firwin,
   Hamming, 20 q + 1 taps, the filter of scipy.signal.decimate) applied as its polyphase resampling does, with
   the window's ends extended linearly (velab.filters: the same numbers, without importing scipy.signal).
   At the reference rig (band 31 Hz) a 1 kHz record is fitted as it is and a 10 kHz record at 1 kHz: the
   model's head has no content above the band, so the calibration sees the same signal and 1/q of the
   out-of-band noise.

The full-rate data stay in the run file; the rate, the filter and the steady head used are
in the fit's settings (``settings["record"]``) and in ``SweepResult.record_rate_hz`` /
``anti_alias_filter``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from velab.filters import fir_decimate, firwin_lowpass
from velab.rig import Rig
from velab.errors import DataError
from velab.fitting.adequacy import assess, baseline_noise
from velab.fitting.friction import fit_rig
from velab.fitting.manoeuvre import CLOSURE_SHAPE, valve_input
from velab.fitting.nuisance import marginalise_single
from velab.fitting.params import FitBounds
from velab.fitting.refine import refine_closure
from velab.fitting.window import MIN_WINDOW_SAMPLES, baseline_slice, steady_head, window_slice
from velab.fitting.results import SweepResult
from velab.fitting.selection import criterion
from velab.fitting.options import FitOptions
from velab.fitting.sweep import SweepContext, fit_sweep
from velab.model import manoeuvre_band_hz

# the fit rate is at least this multiple of the manoeuvre's band (the frequency above which the
# sigmoid's flow spectrum is below 1e-8 of its DC value): 930 Hz at the reference rig
FIT_RATE_PER_BAND = 30.0
FIR_TAPS_PER_Q = 20
# a fitted closure refined with one model's wall, and the continuation naming another: the closure refined
# again with that one's and every model continued, at most this many times (velab.fitting.refine: a closure
# refined with a smaller model's wall had taken up the larger one's fast element, and the larger model,
# named under it all the same, was left 20-120 in n ln F short of its own optimum)
CLOSURE_ROUNDS = 2
# ... and each model is compared at its own closure (a profile likelihood over the closure): a smaller model
# within this many AIC units of the named one gets the closure refined with its wall; named under it, and better
# there than the named model under its own, it is the fit's answer. A closure refined with the S3 wall had given
# S2 (the truth) 6 AIC units behind S3 on two records of six; under its own closure S2 gained 15 in n ln F
RIVAL_DAIC = 20.0


@dataclass(frozen=True)
class PreparedRecord:
    """The calibration data of one record: what the fitter sees, and how it was made."""

    t: np.ndarray  # s from the trigger, at the fit rate
    h: np.ndarray  # head perturbation (m), anti-alias filtered and decimated
    window_s: float
    trigger_time_s: float
    steady_head_m: float
    record_rate_hz: float
    decimation: int
    filter: str
    notes: list[str] = field(default_factory=list)
    # the record's own noise: the pretrigger baseline prepared like the window (velab.fitting.adequacy)
    baseline_noise_m: float | None = None  # None: fewer than adequacy.MIN_BASELINE_SAMPLES at the fit rate
    baseline_lag1: float | None = None
    baseline_samples: int = 0
    # the baseline's samples behind the steady head, counted at the fit rate (record samples / q): the weight
    # of its prior when every model fits the steady head's offset (velab.fitting.offset); 0: no baseline
    steady_samples: float = 0.0
    # the valve position (% open) on t, prepared like the head, if the record holds one
    position: np.ndarray | None = None

    @property
    def fit_rate_hz(self) -> float:
        return self.record_rate_hz / self.decimation

    def describe(self) -> dict:
        """The preparation, as stored with the fit (``settings["record"]``)."""
        return {"record_rate_hz": self.record_rate_hz, "fit_rate_hz": self.fit_rate_hz, "decimation": self.decimation,
                "anti_alias_filter": self.filter, "trigger_time_s": self.trigger_time_s,
                "steady_head_m": self.steady_head_m, "steady_samples": self.steady_samples,
                "window_s": self.window_s, "samples": int(self.h.size)}


def fit_decimation(rig: Rig, record_rate_hz: float) -> int:
    """q: the record is fitted at record_rate / q >= FIT_RATE_PER_BAND x the manoeuvre's band."""
    target = FIT_RATE_PER_BAND * manoeuvre_band_hz(rig)
    qmax = max(1, int(math.floor(record_rate_hz / target * (1 + 1e-9))))
    whole = round(record_rate_hz)
    if abs(record_rate_hz - whole) < 1e-9 * record_rate_hz:
        # a whole fit rate (50 kHz -> 1 kHz, not 943.4 Hz): the largest q below qmax that divides the rate
        for q in range(qmax, 0, -1):
            if whole % q == 0:
                return q
    return qmax


def anti_alias_filter(q: int) -> str:
    if q <= 1:
        return "none"
    return (f"zero-phase FIR low-pass at {1.0 / q:.6g} x Nyquist (firwin, Hamming, {FIR_TAPS_PER_Q * q + 1} taps), "
            f"polyphase decimation by {q}, linear end extension")


def decimate_head(h: np.ndarray, q: int) -> np.ndarray:
    """Anti-alias filtered h sampled at every q-th sample (sample i of the result is at input i q)."""
    if q <= 1:
        return np.array(h, dtype=float)
    return fir_decimate(np.asarray(h, dtype=float), firwin_lowpass(FIR_TAPS_PER_Q * q + 1, 1.0 / q), q)


def prepare_record(t_s, head_m, trigger_time_s: float, rig: Rig, window_s: float | None, *,
                   record_rate_hz: float, position_pct=None) -> PreparedRecord:
    """The calibration data of a record: ``t_s`` on the run's axis (s, increasing), ``head_m`` the
    absolute head there (before and after the trigger), ``window_s`` after the trigger (None: all),
    ``position_pct`` the recorded valve position on ``t_s`` if there is one (the manoeuvre's input,
    velab.fitting.manoeuvre; not used if it is not finite throughout the window).

    Raises DataError (one line) for a window longer than the record, NaN in it, a non-uniform axis."""
    t = np.asarray(t_s, dtype=float)
    head = np.asarray(head_m, dtype=float)
    if t.ndim != 1 or head.shape != t.shape:
        raise DataError(f"time and head must be 1-D arrays of equal length (got {t.shape} and {head.shape})")
    if not (record_rate_hz > 0 and math.isfinite(record_rate_hz)):
        raise DataError(f"sample rate must be positive, got {record_rate_hz!r} Hz")
    if not math.isfinite(trigger_time_s):
        raise DataError("trigger time is not a number")
    dt = 1.0 / record_rate_hz
    steady = steady_head(t, head, trigger_time_s, rig.steady_head_m, record_rate_hz)
    i0 = window_slice(t, trigger_time_s, 0.0, record_rate_hz).start
    avail = (float(t[-1]) - trigger_time_s + dt) if t.size and i0 < t.size else 0.0
    if window_s is None:
        window_s = avail
    if not window_s > 0:
        raise DataError(f"fit window must be positive, got {window_s:g} s")
    if window_s > avail + 0.5 * dt:
        raise DataError(f"fit window {window_s:g} s is longer than the record after the trigger ({avail:.6g} s)")
    i1 = window_slice(t, trigger_time_s, window_s, record_rate_hz).stop
    tw = t[i0:i1] - trigger_time_s
    if tw.size < MIN_WINDOW_SAMPLES:
        raise DataError(f"window too short to calibrate ({tw.size} samples after the trigger)")
    steps = np.diff(tw)
    if np.abs(steps - dt).max() > 1e-3 * dt + 1e-9:
        raise DataError("time axis is not uniform in the fit window (lost samples?)")
    hw = head[i0:i1] - steady
    bad = ~np.isfinite(hw)
    if bad.any():
        j = int(np.argmax(bad))
        raise DataError(f"head is NaN/inf at t = {tw[j]:.6g} s in the fit window ({int(bad.sum())} samples)")
    q = fit_decimation(rig, record_rate_hz)
    hd = decimate_head(hw, q)
    td = tw[::q][: hd.size]
    # the baseline through the window's filter and decimation, so that its variance and F compare
    before = baseline_slice(t, head, trigger_time_s, record_rate_hz)
    base = baseline_noise(head[before] - steady, lambda x: decimate_head(x, q), FIR_TAPS_PER_Q // 2 if q > 1 else 0)
    pos, notes = _window_position(position_pct, t, i0, i1, q, td.size)
    return PreparedRecord(td, hd[: td.size], float(window_s), float(trigger_time_s), steady, float(record_rate_hz), q,
                          anti_alias_filter(q), notes=notes, baseline_noise_m=base.std_m, baseline_lag1=base.lag1,
                          baseline_samples=base.samples, steady_samples=(before.stop - before.start) / q,
                          position=pos)


def _window_position(position_pct, t: np.ndarray, i0: int, i1: int, q: int, n: int):
    """The recorded valve position over the window, filtered and decimated as the head (None if absent
    or not finite throughout: the manoeuvre is then fitted), and a note if it was dropped."""
    if position_pct is None:
        return None, []
    p = np.asarray(position_pct, dtype=float)
    if p.shape != t.shape:
        raise DataError(f"valve position and time must have equal lengths (got {p.shape} and {t.shape})")
    pw = p[i0:i1]
    if not np.all(np.isfinite(pw)):
        return None, ["valve position not finite throughout the window: the manoeuvre is fitted instead"]
    return decimate_head(pw, q)[:n], []


def fit_prepared(rec: PreparedRecord, rig: Rig, options: FitOptions | None = None, *, progress=None) -> SweepResult:
    """``fit_sweep`` on a prepared record, driven by the flow at the valve built from it
    (velab.fitting.manoeuvre; ``options.manoeuvre``: "auto", "fitted" or "rig"); the preparation goes into
    the result (``options.window_s`` is the record's: it is prepared). The single sweep on a prepared record (the
    baseline of benchmarks/fit_speed.py and one_engine.py); the fit path's fit of a record is a stack
    (velab.fitting.recordfit).

    A fitted closure is refined on the whole window with the best model's wall (velab.fitting.refine), then
    every model is calibrated again from its optimum under the refined closure (a continuation). When the
    continuation names another model than the one the closure was refined with, the closure is refined again
    with that model's wall and every model continued once more (``CLOSURE_ROUNDS``): the closure is the named
    model's."""
    opts = (options if options is not None else FitOptions()).replace(window_s=None)
    frig = fit_rig(rig, opts.friction, opts.friction_unsteady)
    vi = valve_input(rec.t, rec.h, frig, rec.window_s, position_pct=rec.position, mode=opts.manoeuvre,
                     shape=CLOSURE_SHAPE)
    # a closure still to be refined: this sweep only seeds the continuation, which makes the time-domain polish;
    # every model fits the steady head's offset, the baseline its prior (velab.fitting.offset)
    refining = vi.source == "fitted"
    ctx = SweepContext(flow=vi.flow, time_domain_polish=not refining,
                       marginalise=None if refining else marginalise_single(frig, rec.t, rec.h, vi),
                       trust_lead=not refining, baseline_n=rec.steady_samples)
    result = fit_sweep(rec.t, rec.h, rig, opts, progress=progress, context=ctx)
    if refining and result.models:
        refined = refine_closure(rec.t, rec.h, frig, vi, result.best, _bounds(result))
        result, vi = _continue(rec, rig, frig, refined, result, opts, progress), refined
    for _ in range(CLOSURE_ROUNDS):
        if not (vi.source == "fitted" and vi.refined_with and result.models and result.best.name != vi.refined_with):
            break
        refined = refine_closure(rec.t, rec.h, frig, vi, result.best, _bounds(result))
        if refined.params == vi.params:  # (the refinement found no better closure for that model)
            vi = refined
            break
        result, vi = _continue(rec, rig, frig, refined, result, opts), refined
    if vi.source == "fitted" and vi.refined_with and result.models:
        result, vi = _own_closures(rec, rig, frig, vi, result, opts)
    result.settings = result.settings.replace(manoeuvre=vi.describe())
    result.notes.append(vi.text)
    # the rates as the record states them (fit_sweep measures its step from the time axis)
    result.sample_rate_hz = rec.fit_rate_hz
    result.record_rate_hz = rec.record_rate_hz
    result.anti_alias_filter = rec.filter
    result.settings = result.settings.replace(record=rec.describe())
    result.notes.extend(rec.notes)
    assess(result, rec, rig)  # noise ratios and warnings (misfit, cavitation, bound)
    return result


def _own_closures(rec: PreparedRecord, rig: Rig, frig: Rig, vi, result: SweepResult, opts: FitOptions):
    """(result, closure): the named model against its nearest smaller rival, each under the closure refined
    with its own wall (``RIVAL_DAIC``). The closure is a nuisance shared by every model, so AIC compares the
    models at their own optimum over it; a closure refined with one wall favours that model. The rival wins
    when the continuation under its closure names it and its criterion there is below the named model's
    under its own; then the whole result is that continuation's (every model under the rival's closure)."""
    best = result.best
    rivals = [f for f in result.models
              if not f.reduced and f.m < best.m and math.isfinite(f.delta_aic) and f.delta_aic < RIVAL_DAIC]
    if not rivals:
        return result, vi
    rival = min(rivals, key=lambda f: f.delta_aic)
    refined = refine_closure(rec.t, rec.h, frig, vi, rival, _bounds(result))
    if refined.params == vi.params:
        return result, vi
    again = _continue(rec, rig, frig, refined, result, opts)
    if again.best.name == rival.name and criterion(again.best, again.selection) < criterion(best, result.selection):
        again.notes.append(f"{rival.name} under the closure refined with its own wall is better than {best.name} "
                           f"under its own: the closure is {rival.name}'s")
        return again, refined
    result.duration_s, result.evaluations = again.duration_s, again.evaluations  # (again's count this fit's too)
    return result, vi


def _continue(rec: PreparedRecord, rig: Rig, frig: Rig, vi, result: SweepResult, opts: FitOptions,
              progress=None) -> SweepResult:
    """Every model of ``result`` calibrated again from its optimum under the refined closure ``vi``; the
    result counts both sweeps' time and work."""
    ctx = SweepContext(lead=result, flow=vi.flow, marginalise=marginalise_single(frig, rec.t, rec.h, vi),
                       trust_lead=False, baseline_n=rec.steady_samples)
    again = fit_sweep(rec.t, rec.h, rig, opts, progress=progress, context=ctx)
    again.settings = again.settings.replace(lead=None)
    again.duration_s += result.duration_s
    again.evaluations += result.evaluations
    return again


def _bounds(result: SweepResult) -> FitBounds | None:
    """The sweep's box for the wall (its ``settings["bounds"]``)."""
    b = result.settings.get("bounds")
    return FitBounds.from_dict(b) if b else None
