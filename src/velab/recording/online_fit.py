"""The online fit: the recorded window -> the fitter, on its own thread, with intermediate fits.

``fit_arguments`` makes the one call into the fitter (velab.fitting.entry.fit_record, the
fit path ``velab fit`` and the GUI's re-fit take too); everything else here is scheduling: intermediate quick fits on the growing
window while the fitter is idle, cancelled when the lead or the final fit starts; the fit path's
lead fit (velab.fitting.lead: the sweep of the window's first part) as soon as that part is in,
while the rest is being recorded; the final fit as soon as the window closes, continuing from
the lead (or computing it, if it failed or does not match); the latency from the window closing
to the result.

A rig with several transducers (velab.recording.transducers) is fitted on every section at once: the
same ``fit_record`` call with the other transducers' heads (``section_heads``), which takes the sections
path (velab.fitting.sections), as ``velab fit`` of the run file does; that fit has no lead and no quick
variant, so only the final fit runs.

With ``settings.fit_process`` (the default) the fits run in a worker process of their own
(velab.fit_worker), started when the manoeuvre is commanded so that its imports are done by the
time the window closes: the recorder's threads and the fit then do not take turns for one interpreter
lock, and at its lower priority the fit never starves them. The worker runs the same ``fit_record`` with the same arguments, so the result is the same
bit for bit. If the worker cannot start or dies, the fit runs here instead, and the run says so.
"""

from __future__ import annotations

import logging
import threading
import time
from concurrent.futures import TimeoutError as FutureTimeout

import numpy as np

from velab.rig import Rig
from velab import fit_worker
from velab.fitting.lead import lead_window_s
from velab.fitting.options import FitOptions

log = logging.getLogger(__name__)
MIN_FIT_WINDOW_S = 2.0


HALTED = "no fit: the run was halted"  # whichever of the fit thread and the run's end says it first


class _Cancelled(Exception):
    pass


class FitError(Exception):
    """The fit raised, in the worker process ("Type: message")."""


def fit_arguments(t_s: np.ndarray, head_m: np.ndarray, trigger_time_s: float, rig: Rig, *, models, window_s: float,
                  method: str, sample_rate_hz: float, quick: bool = False, position_pct=None,
                  section_heads: dict | None = None) -> dict:
    """The arguments of velab.fitting.entry.fit_record for a recorded head record (the run's axis,
    absolute head, from before the trigger): the one fit path, as ``velab fit`` of the run file takes
    it; ``quick`` = no polish, 2 starts (intermediate fits); ``position_pct`` the recorded valve position
    on ``t_s`` (the manoeuvre's input, as ``velab fit`` takes it from the file); ``section_heads`` the
    other transducers' absolute heads on ``t_s`` by name (a rig with several: every section is fitted)."""
    kw = {"polish": False, "starts": 2} if quick else {}
    if section_heads:
        kw["section_heads"] = dict(section_heads)
    return dict(t_s=t_s, head_m=head_m, trigger_time_s=trigger_time_s, rig=rig, window_s=window_s,
                record_rate_hz=sample_rate_hz, models=list(models), method=method, position_pct=position_pct, **kw)


class OnlineFit:
    """Runs fits of the recorded window; publishes ``fit`` events through ``emit``; thread-safe."""

    def __init__(self, rig: Rig, settings, sample_rate_hz: float, emit, message):
        self.rig = rig
        self.sections = len(rig.sections) > 1  # every section at once: the final fit only (module docstring)
        self.s = settings
        self.fs = sample_rate_hz
        self.emit = emit
        self.message = message
        self.result = None
        self.error = ""
        self.latency_s: float | None = None
        self.window_s: float | None = None
        self._final: threading.Thread | None = None
        self._lead: threading.Thread | None = None
        self._lead_result = None  # the lead fit (velab.fitting.lead), when it has ended
        self._running = 0  # fits running (quick, lead, final)
        self._running_lock = threading.Lock()
        self._cancel_quick = threading.Event()
        self._cancel_all = threading.Event()
        self._closed_at: float | None = None
        self._proc = None  # the worker process (start_process)

    def start_process(self) -> None:
        """Start (or take from the pool) the fit process, when the manoeuvre has been commanded: its
        imports (about 1 s of CPU) are done long before the window closes, and never compete with
        the baseline and the trigger (at the fast clock they delayed a trigger by a tenth of a second)."""
        if self._proc is not None or not (self.s.fit_process and self.s.fit):
            return
        try:
            self._proc = fit_worker.acquire()
        except OSError as exc:  # no interpreter to start: fit here
            log.warning("no fit process (%s): the fit runs in the recorder's process", exc)

    def lead_window_s(self) -> float | None:
        """The fit path's lead part of the final window (velab.fitting.lead) for this run's fit options."""
        if not (self.s.fit and self.s.online_fit) or self.sections:
            return None
        return lead_window_s(self.rig, self.s.fit_window_s, FitOptions(method=self.s.fit_method))

    @property
    def busy(self) -> bool:
        return self._running > 0

    @property
    def final_started(self) -> bool:
        return self._final is not None

    def start(self, t: np.ndarray, h: np.ndarray, trigger_time_s: float, window_s: float, *, final: bool,
              position=None, section_heads: dict | None = None) -> None:
        """Start a fit of (t, h) over ``window_s`` after the trigger (a quick one is skipped while another
        runs, and on a rig with several sections); ``section_heads``: the other transducers' heads on t."""
        if not final and self.sections:
            return
        if final:
            if self._final is not None:
                return
            self._closed_at = time.perf_counter()
            self._cancel_quick.set()  # the final fit gets the CPU
        elif self.busy:
            return
        else:
            self._cancel_quick.clear()
        self._spawn("final" if final else "quick", t, h, trigger_time_s, window_s, position, section_heads)

    def start_lead(self, t: np.ndarray, h: np.ndarray, trigger_time_s: float, window_s: float, position=None) -> None:
        """Start the lead fit of a ``window_s`` fit: (t, h) reach the end of the lead's part of the window."""
        if self._lead is not None or self._final is not None:
            return
        self._cancel_quick.set()  # a quick fit still running gives way
        self._lead = self._spawn("lead", t, h, trigger_time_s, window_s, position)

    def _spawn(self, kind: str, t, h, trigger_time_s: float, window_s: float, position=None,
               section_heads=None) -> threading.Thread:
        with self._running_lock:
            self._running += 1
        th = threading.Thread(target=self._work, args=(t, h, trigger_time_s, window_s, kind, position, section_heads),
                              daemon=True,
                              name="velab-recorder-fit" + ("" if kind == "final" else "-" + kind))
        if kind == "final":
            self._final = th
            self.window_s = window_s
        th.start()
        return th

    def refuse(self, why: str) -> None:
        """No final fit, and why (the run's summary and the CLI say it)."""
        if not self.error and self.result is None:
            self.error = why
            self.message(why)

    def _cancelled(self, kind: str) -> bool:
        return self._cancel_all.is_set() or (kind == "quick" and self._cancel_quick.is_set())

    def _lead_for_final(self):
        """The lead fit for the final one: waits for a running lead (a halt ends the wait); True (the
        fit path computes it) if there is none."""
        th = self._lead
        while th is not None and th.is_alive():
            if self._cancel_all.is_set():
                raise _Cancelled()
            th.join(0.05)
        return self._lead_result if self._lead_result is not None else True

    def _fit(self, t, h, trigger_time_s, window_s, kind, position=None, section_heads=None):
        """The fit, in the worker process if there is a live one, else here; raises _Cancelled."""
        final = kind == "final"
        kw = fit_arguments(t, h, trigger_time_s, self.rig, models=self.s.fit_models, window_s=window_s,
                           method=self.s.fit_method, sample_rate_hz=self.fs, quick=kind == "quick",
                           position_pct=position, section_heads=section_heads)
        if final:
            kw["lead"] = self._lead_for_final()
        call = "lead" if kind == "lead" else "record"
        proc = self._proc
        if proc is not None and not proc.alive and final:
            self.message("fit process lost before the final fit: fitting in the recorder's process")
            self._proc, proc = None, None
        if proc is not None:
            job, fut = proc.submit(call, **kw)
            asked = False
            while True:
                try:
                    return fut.result(timeout=0.05)
                except FutureTimeout:
                    pass
                except fit_worker.Cancelled:
                    raise _Cancelled() from None
                except fit_worker.WorkerDied as exc:
                    if self._cancelled(kind):
                        raise _Cancelled() from None
                    if not final:
                        raise
                    # the final fit is not lost with its process: it runs here
                    self.message(f"fit process lost ({exc}): fitting in the recorder's process")
                    break
                except RuntimeError as exc:  # the fit's own error, as the child named it
                    raise FitError(str(exc)) from None
                if self._cancel_all.is_set():
                    proc.kill("halted")  # halt = stop now, not at the fit's next model
                elif not asked and self._cancelled(kind):
                    proc.cancel(job)  # overtaken by the final fit: ends at its next model
                    asked = True

        def progress(done, total, name):
            if self._cancelled(kind):
                raise _Cancelled()

        from velab.fitting import entry  # scipy: only when a fit runs

        return (entry.fit_lead if kind == "lead" else entry.fit_record)(progress=progress, **kw)

    def close(self) -> None:
        """Give the worker process back (kept for the next run if idle; ended if a fit still runs)."""
        proc, self._proc = self._proc, None
        if proc is not None:
            fit_worker.release(proc)

    def _work(self, t, h, trigger_time_s, window_s, kind, position=None, section_heads=None) -> None:
        final = kind == "final"
        try:
            r = self._fit(t, h, trigger_time_s, window_s, kind, position, section_heads)
            if final:
                self.result = r
                self.latency_s = time.perf_counter() - self._closed_at
            elif kind == "lead":
                self._lead_result = r
                if r is None:
                    return  # (this window has no lead fit)
            self.emit("fit", {"result": r, "final": final, "window_s": r.window_s if kind == "lead" else window_s,
                              "lead": kind == "lead"})
        except _Cancelled:
            if final:
                self.error = HALTED
        except FitError as exc:
            if final:
                self.error = f"fit failed: {exc}"
                self.message(self.error)
            elif kind == "lead":
                log.info("lead fit failed (%s): the final fit computes it", exc)
        except Exception as exc:  # noqa: BLE001 - reported as the run's fit error
            log.debug("fit failed", exc_info=True)
            if final:
                self.error = f"fit failed: {type(exc).__name__}: {exc}"
                self.message(self.error)
        finally:
            with self._running_lock:
                self._running -= 1

    def cancel(self) -> None:
        self._cancel_all.set()

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the final fit; True when it is over (or never started)."""
        th = self._final
        if th is None:
            return True
        th.join(timeout)
        return not th.is_alive()
