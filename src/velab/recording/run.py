"""One run (``Run``), driven by the engine's control thread: arm, baseline, trigger (queued if early),
armed timeout, the end (valve safe first, then the stages stopped, the file closed) and the
conclusion (final fit, summary). The run owns its stages and its outcome; the engine
(velab.recording.engine.Recorder) owns the device session, the command queue and the phase."""

from __future__ import annotations

import concurrent.futures as cf
import logging
import math
import threading
import time

from velab.drivers.pressure_source import pressure_source
from velab.drivers.valve import ValveState
from velab.errors import VelabError
from velab.recording import phases as P
from velab.recording.devices import check_steady_flow, check_steady_head
from velab.recording.layout import bench_snapshot, commanded_rig, create_run_file, run_file_name
from velab.recording.online_fit import HALTED, FitOutcome, OnlineFit
from velab.recording.ops import Append, Event, Value
from velab.recording.pressure import PressureStage
from velab.recording.redundancy import RedundancyMonitor, head_mismatch, head_tolerance_m
from velab.recording.safety import ceiling_head, check_manoeuvre, check_output_dir, predict_surge
from velab.recording.slow import SlowChannels
from velab.recording.stroke import fit_stroke
from velab.recording.timeline import Timeline
from velab.recording.transducers import transducer_channels
from velab.recording.trigger import TriggerFailed, make_safe, readback_note, trigger_manoeuvre
from velab.recording.types import DEVICE_ERRORS, DeviceFailure, Hooks, RunHost, RunRefused, RunSummary
from velab.recording.writer import WriterStage, bytes_per_sample
from velab.runfiles.fits import save_fit

log = logging.getLogger(__name__)
PROGRESS_S = 0.25  # wall seconds between progress (countdown) events
FIT_WAIT_S = 600.0  # the conclusion gives up on a final fit after this long, and says so
DEFER = object()  # returned by a command that settles its future later (a queued trigger)


class Run:
    """One armed run: owns its stages (pressure, time line, slow channels, writer, online fit), its
    buffers, its marks and its outcome (``summary``). ``Recorder.arm`` makes one on the control
    thread; the recorder (``rec``) keeps the command queue, the phase machine and the device session,
    and hands a run its commands (trigger, end) and the control thread's ticks."""

    def __init__(self, rec: RunHost):
        self.rec = rec
        self.settings = rec.settings  # (fixed while the run is active: Recorder._set_settings refuses)
        self.path = None
        self.writer: WriterStage | None = None
        self.timeline: Timeline | None = None
        self.source: PressureStage | None = None
        self.slow: SlowChannels | None = None
        self.fit: OnlineFit | None = None
        self.steady: float | None = None  # the steady head: the look before arming, then the baseline's
        self.redundancy: RedundancyMonitor | None = None  # redundant channels, compared at the end
        self.trigger_fut: cf.Future | None = None  # a trigger queued during the baseline (control thread)
        self.armed_timeout_s = 0.0
        self.valve_lost = False  # the safe-state command could not reach the actuator
        self.stroke = None  # the measured stroke (velab.recording.stroke.Stroke), at the end
        self.finished = threading.Event()  # the end has begun: no more samples are taken
        self.done = threading.Event()  # the summary is published
        self.summary: RunSummary | None = None
        self.halt_ev = threading.Event()  # set by Recorder.halt(), from the caller's thread
        self._marks: dict[str, str] = {}  # one line per fault class: the run is flagged
        self._end_request: tuple[str, str] | None = None
        self._end_lock = threading.Lock()  # guards _end_request and _marks (any thread)
        self._last_progress = 0.0
        # the conclusion (control thread): the run's end (status, reason), the fit's outcome (a message from
        # OnlineFit), the moment the conclusion gives up on the final fit
        self._ended_with: tuple[str, str] | None = None
        self._fit_outcome: FitOutcome | None = None
        self._fit_deadline = math.inf
        self._concluding = False
        self.hooks = Hooks(emit=rec.emit, log=self.log, fault=self.fault, request_end=self.request_end)

    @property
    def active(self) -> bool:
        return self.writer is not None and not self.finished.is_set()

    def log(self, kind: str, text: str) -> None:
        """An event into the run file's event log (once the file is open, until it is closed)."""
        w, tl = self.writer, self.timeline
        if w is not None:
            w.put(Event(tl.now_axis if tl is not None else 0.0, kind, text))

    def message(self, text: str) -> None:
        self.rec.emit("message", text)
        self.log("message", text)

    def fault(self, who: str, message: str, kind: str = "error", **extra) -> None:
        """A ``fault`` event (Fault), a line in the run file's event log, and a mark on the run."""
        f = self.rec.make_fault(who, message, kind, **extra)
        self.rec.emit("fault", f)
        self.log("fault", str(f))
        if self.writer is not None:
            with self._end_lock:
                self._marks.setdefault(f"{f.device}:{kind}", str(f))

    def _manoeuvre(self) -> tuple[float, float, float]:
        """The manoeuvre the interlock predicts from and the timeline expects: the settings' (a servo actuator
        runs it), else, for a valve that runs its own stroke (fired), the last stroke measured on this
        connection, else the rig's nominal."""
        s, m = self.settings, self.rec.rig.manoeuvre
        last = getattr(self.rec, "last_stroke", None)
        if last is not None and getattr(self._valve(), "kind", "") == "fired_valve":
            return (s.beta_per_s if s.beta_per_s is not None else last.beta_per_s,
                    s.gamma if s.gamma is not None else last.gamma, s.end_position_pct)
        return (s.beta_per_s if s.beta_per_s is not None else m.beta_per_s,
                s.gamma if s.gamma is not None else m.gamma, s.end_position_pct)

    def _valve(self):
        return self.rec.devices.get(self.rec.roles.get("valve", ""))

    # ------------------------------------------------------------------ arm
    def arm(self):
        """Checks (nothing moves), the run file, the stages, the stream, the actuator armed."""
        s = self.settings
        name = self.rec.roles["pressure"]
        src = pressure_source(self.rec.devices[name], name, self.rec.clock_scale)
        # every transducer of the rig on its channel (the bench's [recorder.transducers]), the valve's first
        transducers = transducer_channels(self.rec.rig, self.rec.bench.transducer_channels, self.rec.bench_where,
                                          src.pressure_channels(), name)
        source = PressureStage(src, tuple(t.adc_channel for t in transducers))
        lo, hi = source.rate_range()
        if not lo <= s.sample_rate_hz <= hi:
            raise VelabError(f"sample rate {s.sample_rate_hz:g} Hz is outside the range of {source.name} "
                             f"({lo:g}..{hi:g} Hz)")
        fs = float(s.sample_rate_hz)
        beta, gamma, end = self._manoeuvre()
        if getattr(self._valve(), "kind", "") == "fired_valve" and (
                s.beta_per_s is not None or s.gamma is not None or s.end_position_pct != 0.0):
            raise VelabError(f"{self.rec.roles['valve']}: a valve fired by a digital line makes its own stroke: a "
                             f"manoeuvre (beta, gamma, end position) cannot be commanded to it (leave them out: the "
                             f"stroke is measured); nothing was armed")
        check_manoeuvre(self.rec.devices[self.rec.roles["valve"]], self.rec.roles["valve"], beta, gamma, end)
        ceiling = ceiling_head(self.rec.rig, s)
        if s.ceiling_head_m is not None and s.ceiling_head_m > ceiling:
            raise VelabError(f"pressure ceiling {s.ceiling_head_m:g} m is above the limiting pressure of the rig "
                             f"({ceiling:.1f} m of head): it cannot be raised past the transducer or the pipe")
        # 1. the output directory, 2. the interlock (pure), 3. readiness: nothing has moved yet
        per_sample = bytes_per_sample(len(transducers))
        check_output_dir(s.out_dir, int((s.pretrigger_s + s.duration_s) * fs * per_sample))
        pred = predict_surge(self.rec.rig, s)
        if not pred.allowed:
            raise RunRefused(pred.message)
        self.rec.check_valve_ready()
        q = check_steady_flow(self.rec.devices[self.rec.roles["flowmeter"]].read_flow, self.rec.device_sleep,
                              self.rec.rig.steady_flow_m3_s, s.flow_tolerance, self.rec.roles["flowmeter"])
        looks = source.look(fs)
        head, quality = looks[transducers[0].adc_channel]
        check_steady_head(head, quality, self.rec.rig.steady_head_m, s.head_range, ceiling)
        for t in transducers[1:]:  # each other transducer plausible too, at its own steady head
            check_steady_head(*looks[t.adc_channel], self.rec.rig.steady_head_at_m(t.position_m), s.head_range,
                              ceiling, transducer=f"{t.name} ({t.adc_channel})")
        self.steady = head
        pred = predict_surge(self.rec.rig, s, head)  # (the limits, cavitation and the ceiling)
        if not pred.allowed:
            raise RunRefused(pred.message)
        # the rate the device will sample at: the time line, the run file and the fit are built on it
        asked = fs
        try:
            fs = source.configure(fs)
        except DEVICE_ERRORS as exc:
            raise DeviceFailure(f"{source.name}: configuring the acquisition failed: {exc}") from None
        # 4. the run file, created before the stream starts (sample 0 = first sample of the stream)
        self.armed_timeout_s = s.armed_timeout(self.rec.bench_armed_timeout_s)
        self.path = run_file_name(s.out_dir, s.run_number)
        setup = bench_snapshot(self.rec.bench, self.rec.roles, self.rec.profiles, self.rec.identities, self.rec.sim)
        about = {"kind": "recording", "bench": self.rec.bench.name, "simulated": self.rec.sim is not None,
                 "material": self.rec.sim.rig.material.name if self.rec.sim is not None else None}
        try:
            w = create_run_file(self.path, self.rec.rig, s, fs=fs, manoeuvre=(beta, gamma, end), steady_head=head,
                                steady_flow=q, predicted_peak=pred.peak_head_m, ceiling=ceiling, device_setup=setup,
                                calibration=source.calibration(), source=about, armed_timeout_s=self.armed_timeout_s,
                                transducers=transducers)
        except VelabError as exc:
            raise RunRefused(str(exc)) from None
        self.writer = WriterStage(w, fs, s.flush_interval_s, self.hooks, per_sample)
        self.source = source
        self.log("operator", f"armed by {s.operator or 'operator'}: {pred.message}")
        self.fit = OnlineFit(commanded_rig(self.rec.rig, beta, gamma), s, fs, self.rec.emit, self.message,
                             deliver=self._fit_delivered)
        mon = self.redundancy = RedundancyMonitor()
        put = self.writer.put

        def write(op):  # the ADC's valve-position channel, as written, for the redundancy check too
            if isinstance(op, Append):
                mon.adc(op.t, op.channels["valve_position"], op.channels["valve_position_quality"],
                        still=not self.timeline.triggered)
            put(op)
        self.timeline = Timeline(s, fs, (beta, gamma, end), ceiling, source.pressure_channel, source.valve_channel,
                                  self.hooks, write, self._window_closed,
                                  on_baseline=lambda: self.rec.submit(lambda: None),
                                  others=transducers[1:], clock_scale=self.rec.clock_scale)
        valve = self.rec.devices[self.rec.roles["valve"]]
        rec = self.rec
        self.slow = SlowChannels(valve, rec.roles["valve"], rec.devices[rec.roles["flowmeter"]], self.hooks,
                                 self.writer.put, lambda: self.timeline.device_axis,
                                 lambda: self.timeline.triggered, s.stall_timeout_s,
                                 # the valve's state reaches the control thread as a message
                                 on_valve=lambda st: (rec.submit(lambda: rec.note_valve(st)), mon.valve(st)),
                                 on_flow=lambda r: mon.flow(r.value) if r.quality.value == "ok"
                                 and not self.timeline.triggered else None)
        # 5. start the stream, then arm the actuator
        try:
            if abs(fs - asked) > 1e-6 * asked:
                self.message(f"{source.name} samples at {fs:.6g} Hz (asked {asked:g} Hz): the run's time axis uses it")
            actual = source.start(s.stall_timeout_s, self.timeline.process, self.hooks)
            if abs(actual - fs) > 1e-6 * fs:
                self.message(f"warning: {source.name} reports {actual:.6g} Hz once running, configured for {fs:.6g} Hz: "
                             f"the run's time axis uses {fs:.6g} Hz")
            valve.set_manoeuvre(beta, gamma, end)
            valve.arm()
        except (DeviceFailure,) + DEVICE_ERRORS as exc:
            self.end(P.FAILED, f"arming failed: {exc}")
            raise DeviceFailure(f"arming failed: {exc}") from None
        self.slow.start()
        self.log("operator", f"actuator armed: beta {beta:g} 1/s, gamma {gamma:g}, end {end:g} %")
        self.rec.set_phase(P.ARMED, path=str(self.path), baseline_s=s.pretrigger_s, remaining_s=s.pretrigger_s,
                            armed_timeout_s=self.armed_timeout_s)
        return self.path

    # ------------------------------------------------------------------ trigger
    def trigger(self, fut: cf.Future):
        """The trigger command (its future ``fut``): queued while the baseline fills, else carried out."""
        if self.rec.phase == P.ARMED and self.active:
            if self.trigger_fut is not None:
                raise VelabError("a trigger is already queued")
            self.trigger_fut = fut
            left = max(0.0, self.settings.pretrigger_s - self.timeline.baseline_s)
            self.rec.emit("trigger", {"queued": True, "baseline_remaining_s": left})
            self.log("operator", f"trigger queued: {left:.2f} s of baseline still to record")
            self.rec.set_phase(P.ARMED, **(self.rec.phase_data | {"trigger_queued": True}))
            return DEFER
        if self.rec.phase != P.TRIGGERABLE or not self.active:
            raise VelabError(f"cannot trigger while {self.rec.phase}" + (" (arm first)" if self.rec.phase in
                                                                     (P.READY, P.DISCONNECTED) + P.END_PHASES else ""))
        return self.fire_trigger()

    def fire_trigger(self) -> float:
        """TRIGGER once; the driver names the outcome (its read-back after a lost reply decides):
        started -> the run goes on (a lost reply is a fault event); not started or refused -> failed,
        the armed valve aborted; unknown (no read-back) -> failed, ABORT sent without asking first."""
        tl, name = self.timeline, self.rec.roles["valve"]
        self.steady = tl.steady_head(self.steady)
        answering, error = self._valve_link()
        if not answering:
            # its polls go unanswered: a TRIGGER would most likely be lost, or start a stroke nobody can watch
            self._trigger_failed(f"does not answer its status polls ({error}): not triggered", ask_valve=False)
        sent = time.time()
        t_est = tl.mark_trigger()
        if self.slow is not None:
            self.slow.hold_valve(True)  # the trigger and its read-back have the bus to themselves
        try:
            out = trigger_manoeuvre(self.rec.devices[name], f" (sent at about t = {t_est:.3f} s)")
        except TriggerFailed as exc:
            self._trigger_failed(str(exc), ask_valve=exc.ask_valve)
        if self.slow is not None:
            self.slow.hold_valve(False)
        note = readback_note(out)
        if note:
            self.fault("valve", note, "protocol")
        # not if the feedback measured it already (a slow read-back); the stroke started by now
        estimate_kept = tl.commit_trigger()
        self.writer.put(Value("manoeuvre/trigger_host_time", sent))
        self.log("operator", f"trigger commanded at about t = {t_est:.3f} s")
        self.rec.set_phase(P.RECORDING, trigger_time_s=tl.counters().trigger_time,
                            fit_window_s=self.settings.fit_window_s, remaining_s=self.settings.fit_window_s)
        if estimate_kept:
            self.rec.emit("trigger", {"trigger_time_s": t_est, "measured": False})
        if self.fit is not None:
            self.fit.start_process()  # after the trigger: its start-up never delays the trigger
        return t_est

    def _trigger_failed(self, message: str, ask_valve: bool):
        """The run fails, naming the valve; the valve commanded safe first (``end``)."""
        name = self.rec.roles["valve"]
        message = message.replace(f"): {name}: ", "): ", 1)  # the driver's message names the device: once is enough
        self.fault("valve", message, "no_response")
        self.end(P.FAILED, f"{name}: {message}", ask_valve=ask_valve)
        raise DeviceFailure(f"{name}: {message}")

    # ------------------------------------------------------------------ timers (control thread)
    def tick(self) -> None:
        if self._ended_with is not None and not self._concluding and time.monotonic() > self._fit_deadline:
            self.fit.refuse(f"no fit: the final fit did not finish within {FIT_WAIT_S:g} s")
            self.fit.cancel()
        if self.timeline is None or not self.active:
            return
        s, tl = self.settings, self.timeline.counters()
        if self.rec.phase == P.ARMED and tl.baseline_complete:
            self.rec.set_phase(P.TRIGGERABLE, path=str(self.path), disarm_in_s=self.armed_timeout_s - tl.baseline_s)
            if self.trigger_fut is not None:
                fut, self.trigger_fut = self.trigger_fut, None
                try:
                    fut.set_result(self.fire_trigger())
                except BaseException as exc:  # noqa: BLE001 - delivered through the queued future
                    fut.set_exception(exc)
        if self.rec.phase in (P.ARMED, P.TRIGGERABLE) and tl.baseline_s >= self.armed_timeout_s:
            msg = (f"armed timeout: no trigger within {self.armed_timeout_s:g} s of arming; "
                   "actuator disarmed (armed manoeuvre cancelled)")
            self.log("disarmed", msg)
            self.rec.emit("message", msg)
            self.end(P.ABORTED, msg)
            return
        now = time.monotonic()
        if now - self._last_progress >= PROGRESS_S:
            self._last_progress = now
            tl = self.timeline.counters()  # (again: a queued trigger may have gone out above)
            if self.rec.phase == P.ARMED:
                d = {"remaining_s": max(0.0, s.pretrigger_s - tl.baseline_s), "what": "baseline"}
            elif self.rec.phase == P.TRIGGERABLE:
                d = {"remaining_s": max(0.0, self.armed_timeout_s - tl.baseline_s), "what": "armed timeout"}
            elif self.rec.phase == P.RECORDING:
                d = {"remaining_s": max(0.0, tl.trigger_time + s.fit_window_s - tl.now_axis), "what": "fit window"}
            else:
                return
            self.rec.emit("progress", {"phase": self.rec.phase, "t_s": tl.now_axis, **d})

    # ------------------------------------------------------------------ the end
    def mark_lines(self) -> list[str]:
        with self._end_lock:
            return list(self._marks.values())

    def ending(self) -> str | None:
        """The status an end was requested with (None: none yet), from any thread."""
        with self._end_lock:
            return self._end_request[0] if self._end_request is not None else None

    def _valve_link(self) -> tuple[bool, str]:
        """(the valve answers its polls, why not): True before the slow channels run."""
        return self.slow.valve_link() if self.slow is not None else (True, "")

    def request_end(self, status: str, reason: str) -> None:
        """From any thread: end the run (the first request wins; later ones are logged)."""
        with self._end_lock:
            if self._end_request is not None or self.finished.is_set():
                return
            self._end_request = (status, reason)
        self.rec.submit(lambda: self.end(status, reason))

    def _window_closed(self, window_s: float, final: bool) -> None:
        """From the acquisition thread: the fit window (or a quick fit's part of it) is in."""
        fit, tl = self.fit, self.timeline
        if fit is None or self.halt_ev.is_set() or (not final and fit.sections):
            return  # (the sections' fit has no quick variant: velab.recording.online_fit)
        ending = self.ending()
        if final and ending in (P.ABORTED, P.FAILED):
            return  # the end decides (no fit of an aborted or failed run)
        try:
            r = tl.fit_window(window_s)
        except ValueError as exc:
            if final:
                fit.refuse(str(exc))
            return
        if r.note and final:
            self.message(r.note)
        if final or (not fit.busy and r.window_s >= window_s):
            fit.start(r.t, r.head, r.trigger_time_s, r.window_s, final=final, position=r.position,
                      section_heads=r.section_heads)

    def _safe_valve(self, ask: bool = True) -> None:
        valve = self.rec.devices.get(self.rec.roles.get("valve", ""))
        if valve is None:
            return
        # it did not answer (its last poll, a read-back): ABORT without asking first
        ask = ask and self._valve_link()[0]
        try:
            line = make_safe(valve, ask)
            if line:
                self.log("operator", line)
        except DEVICE_ERRORS as exc:
            self.valve_lost = True
            self.fault("valve", f"could not be commanded to its safe state: {exc}", "no_response")

    def end(self, status: str, reason: str, ask_valve: bool = True):
        """On the control thread: end the run with ``status`` (idempotent)."""
        if self.finished.is_set() or self.writer is None:
            return self.summary
        with self._end_lock:
            self._end_request = self._end_request or (status, reason)
        if self.slow is not None:
            self.slow.request_stop()  # no new poll queues up in front of the safe-state command
        if status != P.COMPLETED:
            self._safe_valve(ask_valve)  # first: the valve matters more than the file
        self.finished.set()
        problem = self.source.stop() if self.source is not None else ""
        if problem and status == P.COMPLETED:
            self.fault("pressure", problem, "no_response")
        if self.slow is not None and not self.slow.stop(5.0):
            self.fault("recorder", "slow-channel thread did not end within 5 s", "error")
        tl = self.timeline
        tl.finish()
        self._compare_redundant()  # before the status is decided: a disagreement flags the run
        self._measure_stroke()
        if self.trigger_fut is not None:
            fut, self.trigger_fut = self.trigger_fut, None
            fut.set_exception(VelabError(f"trigger cancelled: the run ended before the baseline was in "
                                         f"({status}{': ' + reason if reason else ''})"))
        with self._end_lock:
            mark_lines = list(self._marks.values())
        if status == P.COMPLETED and mark_lines:
            status = P.COMPLETED_WITH_FAULTS
        if self.writer.error and status != P.FAILED:
            status, reason = P.FAILED, "; ".join(x for x in (self.writer.error, reason) if x)
        marks = "; ".join(m for m in mark_lines if m not in reason)  # each said once
        full_reason = "; ".join(x for x in (reason, marks) if x)
        self._decide_fit(status)
        self.log("status", f"{status}: {full_reason}" if full_reason else status)
        self.log("phase", status)
        if not self.writer.close(status, full_reason[:255]):
            self.fault("storage", "the run file could not be closed within 30 s", "storage")
        if not self.valve_lost and self._valve_link()[0]:
            try:  # where the valve ended up (the GUI offers Reset valve when it is closed)
                self.rec.emit_valve(self.rec.devices[self.rec.roles["valve"]].read_status())
            except DEVICE_ERRORS + (KeyError,):
                pass
        self._ended_with = (status, full_reason)
        if not (self.settings.fit and self.fit is not None) or self._fit_outcome is not None:
            self._start_conclusion()  # no fit to wait for, or its outcome is in
        else:  # the outcome arrives as a message (_fit_concluded); the tick gives up after FIT_WAIT_S
            self._fit_deadline = time.monotonic() + FIT_WAIT_S
            if self.fit.final_started and not self.halt_ev.is_set():
                self.rec.set_phase(P.FITTING, status=status, reason=full_reason, path=str(self.path))
        return None

    def _fit_delivered(self, outcome: FitOutcome) -> None:
        """From the thread that settled the final fit (or refused it): its outcome, to the control thread."""
        fut = self.rec.submit(lambda: self._fit_concluded(outcome))
        if fut.done() and fut.exception() is not None:  # (a recorder closing: no control thread any more)
            self._fit_concluded(outcome)

    def _fit_concluded(self, outcome: FitOutcome) -> None:
        """On the control thread: the final fit's outcome; the conclusion starts once the run has ended."""
        if self._fit_outcome is None:
            self._fit_outcome = outcome
        if self._ended_with is not None:
            self._start_conclusion()

    def _start_conclusion(self) -> None:
        if self._concluding:
            return
        self._concluding = True
        status, reason = self._ended_with
        threading.Thread(target=self._conclude, args=(status, reason, self._fit_outcome), daemon=True,
                         name="velab-recorder-conclude").start()

    def _measure_stroke(self) -> None:
        """The sigmoid of the measured valve position (velab.recording.stroke) into the run file and the summary;
        the recorder keeps it: a fired valve's next interlock prediction starts from it."""
        rec = self.timeline.stroke_record() if self.timeline is not None else None
        if rec is None:
            return
        try:
            st = fit_stroke(*rec)
        except Exception as exc:  # noqa: BLE001 - a bug here must not lose the run: say it
            log.exception("stroke")
            self.log("warning", f"the measured stroke could not be fitted: {type(exc).__name__}: {exc}")
            return
        if st is None:
            return
        self.stroke = st
        for key, v in (("beta", st.beta_per_s), ("gamma", st.gamma), ("end_position", st.end_position_pct),
                       ("stroke_rms", st.rms_pct)):
            self.writer.put(Value(f"manoeuvre/measured_{key}", v))
        self.log("stroke", f"measured stroke: beta {st.beta_per_s:.2f} 1/s, gamma {st.gamma:.3f}, end "
                           f"{st.end_position_pct:.1f} %, 90-10 % in {st.closure_s * 1e3:.0f} ms (sigmoid within "
                           f"{st.rms_pct:.2f} % RMS)")

    def _compare_redundant(self) -> None:
        """Redundant measurements compared (velab.recording.redundancy): the actuator's position
        against the ADC's channel, the steady flow against Q0 (faults: the run is flagged), the
        steady head against the rig's (a warning in the file: the data are the transducer's)."""
        mon, tl = self.redundancy, self.timeline
        if mon is None or tl is None:
            return
        try:
            c = tl.counters()
            # a valve that reports no position of its own (fired: its position is an analog channel, the one the
            # recording holds) has nothing to compare with the recorded channel
            independent = getattr(self._valve(), "reports_own_position", True)
            f, n = (mon.position_finding(c.trigger_time, c.trigger_from_feedback, profile=self._manoeuvre())
                    if independent else (None, 0))
            if f is not None:
                self.fault("valve", f.message, f.kind, deviation_pct=round(f.deviation, 3),
                            tolerance_pct=f.tolerance, t_s=f.at_s, polls_compared=n, **f.extras)
            f = mon.flow_finding(self.rec.rig.steady_flow_m3_s, self.settings.flow_tolerance)
            if f is not None:
                self.fault("flowmeter", f.message, f.kind, deviation=round(f.deviation, 5), tolerance=f.tolerance,
                            **f.extras)
            elif c.trigger_time is not None and not mon.flow_readings:  # no verdict: say why, in the file
                self.log("warning", f"{self.rec.roles.get('flowmeter', 'flowmeter')}: no OK reading between arm "
                                    f"and trigger: the steady flow was not compared with the rig's Q0")
            tr = self.rec.rig.transducer
            steady = tl.steady_head(None)
            f = head_mismatch(steady if steady is not None else math.nan, self.rec.rig.steady_head_m,
                              head_tolerance_m(tr.accuracy_fs, tr.full_scale_pa))
            if f is not None:  # a note, not a mark: see docs/recording.md, "Redundant measurements"
                line = f"{self.rec.roles.get('pressure', 'pressure')}: {f.message}"
                self.log("warning", line)
                self.rec.emit("message", f"warning: {line}")
        except Exception as exc:  # noqa: BLE001 - a bug here must not lose the run: say it, flag it
            log.exception("redundancy check")
            self.fault("recorder", f"redundant-measurement check failed: {type(exc).__name__}: {exc}", "error")

    def _decide_fit(self, status: str) -> None:
        """The fit, or why there is none (a run never ends without one or the other)."""
        s, fit, tl = self.settings, self.fit, self.timeline.counters()
        if not s.fit or fit is None:
            return
        if self.halt_ev.is_set():
            fit.cancel()
            fit.refuse(HALTED)
            return
        if fit.final_started or fit.error:
            return
        if tl.trigger_time is None:
            fit.refuse(f"no fit: the run ended ({status}) before the trigger")
        elif not tl.window_closed:
            fit.refuse(f"no fit: the run ended ({status}) {max(0.0, tl.now_axis - tl.trigger_time):.2f} s after "
                       f"the trigger, before the {s.fit_window_s:g} s fit window closed")
        elif status in (P.COMPLETED, P.COMPLETED_WITH_FAULTS, P.STOPPED) or s.online_fit is False:
            self._window_closed(s.fit_window_s, final=True)
            if not fit.final_started and not fit.error:
                fit.refuse("no fit: the recorded window could not be fitted")
        else:
            fit.refuse(f"no fit: the run {status}")

    def _conclude(self, status: str, reason: str, outcome: FitOutcome | None) -> None:
        """On a thread of its own: the fit saved into the run file, the summary handed to the control thread."""
        result, error, latency = None, "", None
        if self.fit is not None:
            self.fit.close()  # the fit process back to the pool (or ended, if a fit still runs in it)
        if outcome is not None:
            result, error, latency = outcome.result, outcome.error, outcome.latency_s
            if result is not None and self.path is not None:
                try:
                    save_fit(self.path, result, name="online")
                except Exception as exc:  # noqa: BLE001 - the fit is still in the summary
                    error = f"fit not saved in the run file: {exc}"
                    self.rec.emit("message", error)
        tl = self.timeline.counters()
        summary = RunSummary(
            path=self.path, status=status, reason=reason, n_samples=tl.n_written, lost_samples=tl.lost,
            peak_head_m=tl.peak if math.isfinite(tl.peak) else float("nan"), fit=result,
            best_model=result.best.name if result is not None else None,
            wave_speed_m_s=float(result.best.wave_speed_m_s) if result is not None else None,
            trigger_time_s=tl.trigger_time, steady_head_m=self.steady, gaps=tl.gaps,
            fit_latency_s=latency if result is not None else None, fit_error=error,
            faults=self.mark_lines(), flagged_samples=tl.flagged, stroke=self.stroke)
        fut = self.rec.submit(lambda: self._finish(summary))  # the phase is the control thread's
        if fut.done() and fut.exception() is not None:  # (a recorder closing: no control thread any more)
            self._finish(summary)

    def _finish(self, summary: RunSummary) -> None:
        self.summary = summary
        if summary.stroke is not None:  # (the control thread's): a fired valve's next prediction starts from it
            self.rec.last_stroke = summary.stroke
        self.rec.set_phase(summary.status, status=summary.status, reason=summary.reason, path=str(self.path))
        self.rec.emit("done", summary)
        self.done.set()
