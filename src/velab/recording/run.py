"""One run, on the engine's control thread: arm, baseline, trigger (queued if early), armed timeout,
the end (valve safe first, then the stages stopped, the file closed) and the conclusion (final fit,
summary). Part of the engine (``Recorder`` derives from ``RunControl``)."""

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
from velab.recording.online_fit import HALTED, OnlineFit
from velab.recording.ops import Append, Value
from velab.recording.pressure import PressureStage
from velab.recording.redundancy import RedundancyMonitor, head_mismatch, head_tolerance_m
from velab.recording.safety import ceiling_head, check_output_dir, predict_surge
from velab.recording.slow import SlowChannels
from velab.recording.timeline import Timeline
from velab.recording.trigger import TriggerFailed, make_safe, readback_note, trigger_manoeuvre
from velab.recording.types import DEVICE_ERRORS, DeviceFailure, RunRefused, RunSummary
from velab.recording.writer import BYTES_PER_SAMPLE, WriterStage
from velab.runfiles.fits import save_fit

log = logging.getLogger(__name__)
PROGRESS_S = 0.25  # wall seconds between progress (countdown) events
FIT_WAIT_S = 600.0  # the conclusion gives up on a final fit after this long, and says so
DEFER = object()  # returned by a command that settles its future later (a queued trigger)


class RunControl:
    def _init_run_state(self) -> None:
        self.path = None
        self._writer: WriterStage | None = None
        self._timeline: Timeline | None = None
        self._source: PressureStage | None = None
        self._slow: SlowChannels | None = None
        self._fit: OnlineFit | None = None
        self._steady: float | None = None
        self._marks: dict[str, str] = {}
        self._end_request: tuple[str, str] | None = None
        self._end_lock = threading.Lock()
        self._finished = threading.Event()
        self._done = threading.Event()
        self._summary: RunSummary | None = None
        self._trigger_fut: cf.Future | None = None
        self._armed_at_samples = 0
        self._armed_timeout_s = 0.0
        self._last_progress = 0.0
        self._halt = threading.Event()  # set by halt(), from the caller's thread
        self._fit_error = ""
        self._valve_lost = False  # the safe-state command could not reach the actuator
        self._redundancy: RedundancyMonitor | None = None  # redundant channels, compared at the end

    def _run_active(self) -> bool:
        return self._writer is not None and not self._finished.is_set()

    def _manoeuvre(self) -> tuple[float, float, float]:
        s, m = self.settings, self.rig.manoeuvre
        return (s.beta_per_s if s.beta_per_s is not None else m.beta_per_s,
                s.gamma if s.gamma is not None else m.gamma, s.end_position_pct)

    # ------------------------------------------------------------------ arm
    def _do_arm(self):
        if self._run_active() or self.phase in (P.CONNECTING, P.FITTING):
            raise VelabError(f"cannot arm while {self.phase}")
        if not self._devices_ready():
            self._do_connect()
        s = self.settings
        self._init_run_state()
        name = self.roles["pressure"]
        source = PressureStage(pressure_source(self.devices[name], name, getattr(self.clock, "scale", 1.0)
                                               if self.clock is not None else 1.0))
        lo, hi = source.rate_range()
        if not lo <= s.sample_rate_hz <= hi:
            raise VelabError(f"sample rate {s.sample_rate_hz:g} Hz is outside the range of {source.name} "
                             f"({lo:g}..{hi:g} Hz)")
        fs = float(s.sample_rate_hz)
        beta, gamma, end = self._manoeuvre()
        ceiling = ceiling_head(self.rig, s)
        if s.ceiling_head_m is not None and s.ceiling_head_m > ceiling:
            raise VelabError(f"pressure ceiling {s.ceiling_head_m:g} m is above the limiting pressure of the rig "
                             f"({ceiling:.1f} m of head): it cannot be raised past the transducer or the pipe")
        # 1. the output directory, 2. the interlock (pure), 3. readiness: nothing has moved yet
        check_output_dir(s.out_dir, int((s.pretrigger_s + s.duration_s) * fs * BYTES_PER_SAMPLE))
        pred = predict_surge(self.rig, s)
        if not pred.allowed:
            raise RunRefused(pred.message)
        self._check_valve_ready()
        q = check_steady_flow(self.devices[self.roles["flowmeter"]].read_flow, self._sleep,
                              self.rig.steady_flow_m3_s, s.flow_tolerance, self.roles["flowmeter"])
        head, quality = source.look(fs)
        check_steady_head(head, quality, self.rig.steady_head_m, s.head_range, ceiling)
        self._steady = head
        pred = predict_surge(self.rig, s, head)
        if not pred.allowed:
            raise RunRefused(pred.message)
        if pred.peak_head_m >= ceiling:
            self._emit("message", f"warning: predicted peak {pred.peak_head_m:.1f} m is above the pressure "
                                  f"ceiling {ceiling:.1f} m: the run will probably be aborted")
        # 4. the run file, created before the stream starts (sample 0 = first sample of the stream)
        self._armed_timeout_s = s.armed_timeout(self.bench_armed_timeout_s)
        self.path = run_file_name(s.out_dir, s.run_number)
        setup = bench_snapshot(self.bench, self.roles, self.profiles, self.identities, self.sim)
        src = {"kind": "recording", "bench": self.bench.name, "simulated": self.sim is not None,
               "material": self.sim.rig.material.name if self.sim is not None else None}
        try:
            w = create_run_file(self.path, self.rig, s, fs=fs, manoeuvre=(beta, gamma, end), steady_head=head,
                                steady_flow=q, predicted_peak=pred.peak_head_m, ceiling=ceiling, device_setup=setup,
                                calibration=source.calibration(), source=src, armed_timeout_s=self._armed_timeout_s)
        except VelabError as exc:
            raise RunRefused(str(exc)) from None
        self._writer = WriterStage(w, fs, s.flush_interval_s, self.hooks)
        self._source = source
        self._log("operator", f"armed by {s.operator or 'operator'}: {pred.message}")
        self._fit = OnlineFit(commanded_rig(self.rig, beta, gamma), s, fs, self._emit, self._message)
        mon = self._redundancy = RedundancyMonitor()
        put = self._writer.put

        def write(op):  # the ADC's valve-position channel, as written, for the redundancy check too
            if isinstance(op, Append):
                mon.adc(op.t, op.channels["valve_position"], op.channels["valve_position_quality"],
                        still=not self._timeline.triggered)
            put(op)
        self._timeline = Timeline(s, fs, (beta, gamma, end), ceiling, source.pressure_channel, source.valve_channel,
                                  self.hooks, write, self._window_closed,
                                  on_baseline=lambda: self._submit(lambda: None),
                                  lead_window_s=self._fit.lead_window_s(), on_lead=self._lead_ready)
        valve = self.devices[self.roles["valve"]]
        self._slow = SlowChannels(valve, self.roles["valve"], self.devices[self.roles["flowmeter"]], self.hooks,
                                  self._writer.put, lambda: self._timeline.now_axis,
                                  lambda: self._timeline.triggered, s.stall_timeout_s,
                                  # the valve's state reaches the control thread as a message
                                  on_valve=lambda st: (self._submit(lambda: self._note_valve(st)), mon.valve(st)),
                                  on_flow=lambda r: mon.flow(r.value) if r.quality.value == "ok"
                                  and not self._timeline.triggered else None)
        # 5. start the stream, then arm the actuator
        try:
            actual = source.start(fs, s.stall_timeout_s, self._timeline.process, self.hooks)
            if abs(actual - fs) > 1e-6 * fs:
                self._message(f"{source.name} runs at {actual:g} Hz (asked {fs:g} Hz)")
            valve.set_manoeuvre(beta, gamma, end)
            valve.arm()
            valve.wait_for({ValveState.ARMED}, timeout_s=5.0)
        except (DeviceFailure,) + DEVICE_ERRORS as exc:
            self._do_end(P.FAILED, f"arming failed: {exc}")
            raise DeviceFailure(f"arming failed: {exc}") from None
        self._slow.start()
        self._log("operator", f"actuator armed: beta {beta:g} 1/s, gamma {gamma:g}, end {end:g} %")
        self._set_phase(P.ARMED, path=str(self.path), baseline_s=s.pretrigger_s, remaining_s=s.pretrigger_s,
                        armed_timeout_s=self._armed_timeout_s)
        return self.path

    # ------------------------------------------------------------------ trigger
    def _do_trigger(self):
        if self.phase == P.ARMED and self._run_active():
            if self._trigger_fut is not None:
                raise VelabError("a trigger is already queued")
            self._trigger_fut = self._current_fut
            left = max(0.0, self.settings.pretrigger_s - self._timeline.baseline_s)
            self._emit("trigger", {"queued": True, "baseline_remaining_s": left})
            self._log("operator", f"trigger queued: {left:.2f} s of baseline still to record")
            self._set_phase(P.ARMED, **(self.phase_data | {"trigger_queued": True}))
            return DEFER
        if self.phase != P.TRIGGERABLE or not self._run_active():
            raise VelabError(f"cannot trigger while {self.phase}" + (" (arm first)" if self.phase in
                                                                     (P.READY, P.DISCONNECTED) + P.END_PHASES else ""))
        return self._fire_trigger()

    def _fire_trigger(self) -> float:
        """TRIGGER once; the driver names the outcome (its read-back after a lost reply decides):
        started -> the run goes on (a lost reply is a fault event); not started or refused -> failed,
        the armed valve aborted; unknown (no read-back) -> failed, ABORT sent without asking first."""
        tl, name = self._timeline, self.roles["valve"]
        self._steady = tl.steady_head(self._steady)
        answering, error = self._valve_link()
        if not answering:
            # its polls go unanswered: a TRIGGER would most likely be lost, or start a stroke nobody can watch
            self._trigger_failed(f"does not answer its status polls ({error}): not triggered", ask_valve=False)
        sent = time.time()
        t_est = tl.mark_trigger(sent, getattr(self.clock, "scale", 1.0) if self.clock is not None else 1.0)
        if self._slow is not None:
            self._slow.hold_valve(True)  # the trigger and its read-back have the bus to themselves
        try:
            out = trigger_manoeuvre(self.devices[name], f" (sent at about t = {t_est:.3f} s)")
        except TriggerFailed as exc:
            self._trigger_failed(str(exc), ask_valve=exc.ask_valve)
        if self._slow is not None:
            self._slow.hold_valve(False)
        note = readback_note(out)
        if note:
            self._fault("valve", note, "protocol")
        estimate_kept = tl.commit_trigger()  # not if the feedback measured it already (a slow read-back)
        self._writer.put(Value("manoeuvre/trigger_host_time", sent))
        self._log("operator", f"trigger commanded at about t = {t_est:.3f} s")
        self._set_phase(P.RECORDING, trigger_time_s=tl.counters().trigger_time, fit_window_s=self.settings.fit_window_s,
                        remaining_s=self.settings.fit_window_s)
        if estimate_kept:
            self._emit("trigger", {"trigger_time_s": t_est, "measured": False})
        if self._fit is not None:
            self._fit.start_process()  # after the trigger: its start-up never delays the trigger
        return t_est

    def _trigger_failed(self, message: str, ask_valve: bool):
        """The run fails, naming the valve; the valve commanded safe first (``_do_end``)."""
        name = self.roles["valve"]
        message = message.replace(f"): {name}: ", "): ", 1)  # the driver's message names the device: once is enough
        self._fault("valve", message, "no_response")
        self._do_end(P.FAILED, f"{name}: {message}", ask_valve=ask_valve)
        raise DeviceFailure(f"{name}: {message}")

    # ------------------------------------------------------------------ timers (control thread)
    def _tick(self) -> None:
        if self._timeline is None or not self._run_active():
            return
        s, tl = self.settings, self._timeline.counters()
        if self.phase == P.ARMED and tl.baseline_complete:
            self._set_phase(P.TRIGGERABLE, path=str(self.path), disarm_in_s=self._armed_timeout_s - tl.baseline_s)
            if self._trigger_fut is not None:
                fut, self._trigger_fut = self._trigger_fut, None
                try:
                    fut.set_result(self._fire_trigger())
                except BaseException as exc:  # noqa: BLE001 - delivered through the queued future
                    fut.set_exception(exc)
        if self.phase in (P.ARMED, P.TRIGGERABLE) and tl.baseline_s >= self._armed_timeout_s:
            msg = (f"armed timeout: no trigger within {self._armed_timeout_s:g} s of arming; "
                   "actuator disarmed (armed manoeuvre cancelled)")
            self._log("disarmed", msg)
            self._emit("message", msg)
            self._do_end(P.ABORTED, msg)
            return
        now = time.monotonic()
        if now - self._last_progress >= PROGRESS_S:
            self._last_progress = now
            tl = self._timeline.counters()  # (again: a queued trigger may have gone out above)
            if self.phase == P.ARMED:
                d = {"remaining_s": max(0.0, s.pretrigger_s - tl.baseline_s), "what": "baseline"}
            elif self.phase == P.TRIGGERABLE:
                d = {"remaining_s": max(0.0, self._armed_timeout_s - tl.baseline_s), "what": "armed timeout"}
            elif self.phase == P.RECORDING:
                d = {"remaining_s": max(0.0, tl.trigger_time + s.fit_window_s - tl.now_axis), "what": "fit window"}
            else:
                return
            self._emit("progress", {"phase": self.phase, "t_s": tl.now_axis, **d})

    # ------------------------------------------------------------------ the end
    def _mark_lines(self) -> list[str]:
        with self._end_lock:
            return list(self._marks.values())

    def _ending(self) -> str | None:
        """The status an end was requested with (None: none yet), from any thread."""
        with self._end_lock:
            return self._end_request[0] if self._end_request is not None else None

    def _valve_link(self) -> tuple[bool, str]:
        """(the valve answers its polls, why not): True before the slow channels run."""
        return self._slow.valve_link() if self._slow is not None else (True, "")

    def _request_end(self, status: str, reason: str) -> None:
        """From any thread: end the run (the first request wins; later ones are logged)."""
        with self._end_lock:
            if self._end_request is not None or self._finished.is_set():
                return
            self._end_request = (status, reason)
        self._submit(lambda: self._do_end(status, reason))

    def _lead_ready(self) -> None:
        """From the acquisition thread: the lead's part of the window is in: its fit starts now,
        while the rest is recorded (the final fit then continues from it)."""
        fit, tl = self._fit, self._timeline
        if fit is None or self._halt.is_set() or self._ending() is not None or tl.lead_window_s is None:
            return
        try:
            t, h, trigger, _, _, pos = tl.fit_window(tl.lead_window_s)
        except ValueError:
            return  # (the final fit says why there is no fit)
        fit.start_lead(t, h, trigger, self.settings.fit_window_s, position=pos)

    def _window_closed(self, window_s: float, final: bool) -> None:
        """From the acquisition thread: the fit window (or a quick fit's part of it) is in."""
        fit, tl = self._fit, self._timeline
        if fit is None or self._halt.is_set():
            return
        ending = self._ending()
        if final and ending in (P.ABORTED, P.FAILED):
            return  # the end decides (no fit of an aborted or failed run)
        try:
            t, h, trigger, w, note, pos = tl.fit_window(window_s)
        except ValueError as exc:
            if final:
                fit.refuse(str(exc))
            return
        if note and final:
            self._message(note)
        if final or (not fit.busy and w >= window_s):
            fit.start(t, h, trigger, w, final=final, position=pos)

    def _safe_valve(self, ask: bool = True) -> None:
        valve = self.devices.get(self.roles.get("valve", ""))
        if valve is None:
            return
        # it did not answer (its last poll, a read-back): ABORT without asking first
        ask = ask and self._valve_link()[0]
        try:
            line = make_safe(valve, ask)
            if line:
                self._log("operator", line)
        except DEVICE_ERRORS as exc:
            self._valve_lost = True
            self._fault("valve", f"could not be commanded to its safe state: {exc}", "no_response")

    def _do_end(self, status: str, reason: str, ask_valve: bool = True):
        """On the control thread: end the run with ``status`` (idempotent)."""
        if self._finished.is_set() or self._writer is None:
            return self._summary
        with self._end_lock:
            self._end_request = self._end_request or (status, reason)
        if self._slow is not None:
            self._slow.request_stop()  # no new poll queues up in front of the safe-state command
        if status != P.COMPLETED:
            self._safe_valve(ask_valve)  # first: the valve matters more than the file
        self._finished.set()
        problem = self._source.stop() if self._source is not None else ""
        if problem and status == P.COMPLETED:
            self._fault("pressure", problem, "no_response")
        if self._slow is not None and not self._slow.stop(5.0):
            self._fault("recorder", "slow-channel thread did not end within 5 s", "error")
        tl = self._timeline
        tl.finish()
        self._compare_redundant()  # before the status is decided: a disagreement flags the run
        if self._trigger_fut is not None:
            fut, self._trigger_fut = self._trigger_fut, None
            fut.set_exception(VelabError(f"trigger cancelled: the run ended before the baseline was in "
                                         f"({status}{': ' + reason if reason else ''})"))
        with self._end_lock:
            mark_lines = list(self._marks.values())
        if status == P.COMPLETED and mark_lines:
            status = P.COMPLETED_WITH_FAULTS
        if self._writer.error and status != P.FAILED:
            status, reason = P.FAILED, "; ".join(x for x in (self._writer.error, reason) if x)
        marks = "; ".join(m for m in mark_lines if m not in reason)  # each said once
        full_reason = "; ".join(x for x in (reason, marks) if x)
        self._decide_fit(status)
        self._log("status", f"{status}: {full_reason}" if full_reason else status)
        self._log("phase", status)
        if not self._writer.close(status, full_reason[:255]):
            self._fault("storage", "the run file could not be closed within 30 s", "storage")
        if not self._valve_lost and self._valve_link()[0]:
            try:  # where the valve ended up (the GUI offers Reset valve when it is closed)
                self._emit_valve(self.devices[self.roles["valve"]].read_status())
            except DEVICE_ERRORS + (KeyError,):
                pass
        fit_pending = self._fit is not None and self._fit.final_started and not self._halt.is_set()
        if fit_pending:
            self._set_phase(P.FITTING, status=status, reason=full_reason, path=str(self.path))
        threading.Thread(target=self._conclude, args=(status, full_reason), daemon=True,
                         name="velab-recorder-conclude").start()
        return None

    def _compare_redundant(self) -> None:
        """Redundant measurements compared (velab.recording.redundancy): the actuator's position
        against the ADC's channel, the steady flow against Q0 (faults: the run is flagged), the
        steady head against the rig's (a warning in the file: the data are the transducer's)."""
        mon, tl = self._redundancy, self._timeline
        if mon is None or tl is None:
            return
        try:
            c = tl.counters()
            f, n = mon.position_finding(c.trigger_time, c.trigger_from_feedback)
            if f is not None:
                self._fault("valve", f.message, f.kind, deviation_pct=round(f.deviation, 3),
                            tolerance_pct=f.tolerance, t_s=f.at_s, polls_compared=n, **f.extras)
            f = mon.flow_finding(self.rig.steady_flow_m3_s, self.settings.flow_tolerance)
            if f is not None:
                self._fault("flowmeter", f.message, f.kind, deviation=round(f.deviation, 5), tolerance=f.tolerance,
                            **f.extras)
            tr = self.rig.transducer
            steady = tl.steady_head(None)
            f = head_mismatch(steady if steady is not None else math.nan, self.rig.steady_head_m,
                              head_tolerance_m(tr.accuracy_fs, tr.full_scale_pa))
            if f is not None:  # a note, not a mark: see docs/recording.md, "Redundant measurements"
                line = f"{self.roles.get('pressure', 'pressure')}: {f.message}"
                self._log("warning", line)
                self._emit("message", f"warning: {line}")
        except Exception as exc:  # noqa: BLE001 - a bug here must not lose the run: say it, flag it
            log.exception("redundancy check")
            self._fault("recorder", f"redundant-measurement check failed: {type(exc).__name__}: {exc}", "error")

    def _decide_fit(self, status: str) -> None:
        """The fit, or why there is none (a run never ends without one or the other)."""
        s, fit, tl = self.settings, self._fit, self._timeline.counters()
        if not s.fit or fit is None:
            return
        if self._halt.is_set():
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

    def _conclude(self, status: str, reason: str) -> None:
        fit = self._fit
        result, error, latency = None, "", None
        if fit is not None:
            if not fit.wait(FIT_WAIT_S):
                fit.cancel()
                fit.refuse(f"no fit: the final fit did not finish within {FIT_WAIT_S:g} s")
            fit.close()  # the fit process back to the pool (or ended, if a fit still runs in it)
            result, error, latency = fit.result, fit.error, fit.latency_s
            if result is not None and self.path is not None:
                try:
                    save_fit(self.path, result, name="online")
                except Exception as exc:  # noqa: BLE001 - the fit is still in the summary
                    error = f"fit not saved in the run file: {exc}"
                    self._emit("message", error)
        tl = self._timeline.counters()
        summary = RunSummary(
            path=self.path, status=status, reason=reason, n_samples=tl.n_written, lost_samples=tl.lost,
            peak_head_m=tl.peak if math.isfinite(tl.peak) else float("nan"), fit=result,
            best_model=result.best.name if result is not None else None,
            wave_speed_m_s=float(result.best.wave_speed_m_s) if result is not None else None,
            trigger_time_s=tl.trigger_time, steady_head_m=self._steady, gaps=tl.gaps,
            fit_latency_s=latency if result is not None else None, fit_error=error,
            faults=self._mark_lines(), flagged_samples=tl.flagged)
        fut = self._submit(lambda: self._finish(summary))  # the phase is the control thread's
        if fut.done() and fut.exception() is not None:  # (a recorder closing: no control thread any more)
            self._finish(summary)

    def _finish(self, summary: RunSummary) -> None:
        self._summary = summary
        self._set_phase(summary.status, status=summary.status, reason=summary.reason, path=str(self.path))
        self._emit("done", summary)
        self._done.set()
