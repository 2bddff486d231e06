"""The online fit: the recorded window -> the fit service, with intermediate fits; its outcome a message.

Everything here is scheduling; every fit is a :class:`velab.fitservice.FitRequest` of the recorded
:class:`~velab.fitservice.Record` with the run's :class:`~velab.fitservice.FitOptions`, the request
``velab fit`` of the run file makes too (velab.fitservice.execute -> velab.fitting.entry.fit_record):

* intermediate quick fits (no polish, two starts) on the growing window while the fitter is idle,
  cancelled when the final fit starts;
* the final fit as soon as the window closes; the latency from the window closing to the result.

A rig with several transducers (velab.recording.transducers) is fitted on every section at once: the same
request with the other transducers' heads, which takes the sections path (velab.fitting.sections), as
``velab fit`` of the run file does; that fit has no quick variant, so only the final fit runs.

With ``settings.fit_process`` (the default) the fits run on the service's worker-process backend (one
fit process of velab.fit_worker, started when the manoeuvre is commanded so that its imports are done
by the time the window closes; at its lower priority it never starves the recorder's threads); the
result is the same bit for bit. If that process cannot start or dies, the final fit runs on the
in-process backend instead, and the run says so. A halt kills the process at once.

Threads: ``start`` is called from the acquisition thread, ``refuse``/``cancel``/``close``
from the control thread (``cancel`` also from a halting caller), the fits' outcomes arrive on the
service's threads. All state is under one lock; the final outcome (:class:`FitOutcome`) is delivered
once, through ``deliver`` (the run posts it to the control thread), and nothing of this object needs
to be read by another thread.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, replace

import numpy as np

from velab.fitservice.errors import FitCancelled, FitFailed, FitWorkerDied
from velab.fitting.options import FitOptions
from velab.fitservice.request import FitRequest, Record
from velab.fitservice.service import FitService
from velab.rig import Rig

log = logging.getLogger(__name__)
MIN_FIT_WINDOW_S = 2.0
QUICK = {"polish": False, "starts": 2}  # an intermediate fit's choices over the run's

HALTED = "no fit: the run was halted"  # whichever of the fit and the run's end says it first


@dataclass(frozen=True)
class FitOutcome:
    """The final fit of a run, or why there is none: ``result`` (a SweepResult) or ``error`` (one line),
    ``latency_s`` from the window closing to the result, ``window_s`` the final window."""

    result: object = None
    error: str = ""
    latency_s: float | None = None
    window_s: float | None = None


def run_choices(settings) -> FitOptions:
    """The fit choices of a recording's settings (its final fit; quick fits add ``QUICK``)."""
    return FitOptions(models=tuple(settings.fit_models), method=settings.fit_method)


class OnlineFit:
    """Runs the fits of the recorded window (module docstring); publishes ``fit`` events through
    ``emit`` and says what happened through ``message``; ``deliver(FitOutcome)`` is called once with the
    final outcome (from whichever thread settles it). Thread-safe."""

    def __init__(self, rig: Rig, settings, sample_rate_hz: float, emit, message, deliver=None):
        self.rig = rig
        self.sections = len(rig.sections) > 1  # every section at once: the final fit only (module docstring)
        self.s = settings
        self.fs = sample_rate_hz
        self.emit = emit
        self.message = message
        self._deliver = deliver
        self.choices = run_choices(settings)
        self._here = FitService.in_thread()
        self._lock = threading.Lock()
        self._proc: FitService | None = None  # the worker-process backend (start_process)
        self._running: set = set()  # futures of the fits running (quick, final)
        self._quick: set = set()
        self._final_started = False
        self._closed_at: float | None = None
        self._window_s: float | None = None
        self._final = None  # the final fit's future
        self._halted = False
        self._outcome: FitOutcome | None = None
        self._done = threading.Event()

    # ------------------------------------------------------------------ state (locked reads)
    def start_process(self) -> None:
        """Start (or take from the pool) the fit process, when the manoeuvre has been commanded: its
        imports (about 1 s of CPU) are done long before the window closes, and never compete with
        the baseline and the trigger (at the fast clock they delayed a trigger by a tenth of a second)."""
        with self._lock:
            if self._proc is not None or not (self.s.fit_process and self.s.fit):
                return
        try:
            proc = FitService.processes(1, replace_dead=False, start=True)
        except OSError as exc:  # no interpreter to start: fit here
            log.warning("no fit process (%s): the fit runs in the recorder's process", exc)
            return
        with self._lock:
            self._proc = proc

    @property
    def busy(self) -> bool:
        with self._lock:
            return bool(self._running)

    @property
    def final_started(self) -> bool:
        with self._lock:
            return self._final_started

    def outcome(self) -> FitOutcome | None:
        """The final outcome, once delivered."""
        with self._lock:
            return self._outcome

    # what the outcome says (tests, scripts; the run takes the delivered FitOutcome)
    @property
    def result(self):
        o = self.outcome()
        return o.result if o is not None else None

    @property
    def error(self) -> str:
        o = self.outcome()
        return o.error if o is not None else ""

    @property
    def latency_s(self) -> float | None:
        o = self.outcome()
        return o.latency_s if o is not None else None

    # ------------------------------------------------------------------ starting fits
    def _request(self, t, h, trigger_time_s, window_s, kind, position=None, section_heads=None):
        choices = replace(self.choices, **QUICK) if kind == "quick" else self.choices
        src = Record(t, h, trigger_time_s, self.rig, self.fs, position_pct=position, section_heads=section_heads or ())
        return FitRequest(src, window_s, choices, label="recorder-" + kind)

    def _service(self, final: bool) -> FitService:
        """The process backend while its process lives, else this process (the final fit says so)."""
        with self._lock:
            proc = self._proc
        if proc is None:
            return self._here
        if final and not proc.alive:
            self.message("fit process lost before the final fit: fitting in the recorder's process")
            with self._lock:
                if self._proc is proc:
                    self._proc = None
            proc.close()
            return self._here
        return proc  # (a quick fit on a lost process fails at once)

    def start(self, t: np.ndarray, h: np.ndarray, trigger_time_s: float, window_s: float, *, final: bool,
              position=None, section_heads: dict | None = None) -> None:
        """Start a fit of (t, h) over ``window_s`` after the trigger (a quick one is skipped while another
        runs, and on a rig with several sections); ``section_heads``: the other transducers' heads on t."""
        if not final and self.sections:
            return
        if not final:
            with self._lock:
                if self._running or self._final_started or self._halted:
                    return
                # (reserved under the lock: a second quick fit is skipped until this one is submitted)
                token = object()
                self._running.add(token)
            try:
                self._submit("quick", self._request(t, h, trigger_time_s, window_s, "quick", position))
            finally:
                with self._lock:
                    self._running.discard(token)
            return
        with self._lock:
            if self._final_started:
                return
            self._final_started = True
            self._closed_at = time.perf_counter()
            self._window_s = window_s
            quick = list(self._quick)
        for f in quick:
            f.cancel_fit()  # the final fit gets the CPU (a quick fit in the process ends at its next model)
        self._start_final(t, h, trigger_time_s, window_s, position, section_heads)

    def _submit(self, kind: str, request: FitRequest, service: FitService | None = None):
        fut = (service or self._service(kind == "final")).submit(request)
        with self._lock:
            self._running.add(fut)
            if kind == "quick":
                self._quick.add(fut)
            elif kind == "final":
                self._final = fut
            halted = self._halted
        if halted:
            fut.cancel_fit(kill=True)
        fut.add_done_callback(lambda f: self._ended(kind, request, f))
        return fut

    def _start_final(self, t, h, trigger_time_s, window_s, position, section_heads) -> None:
        with self._lock:
            halted = self._halted
        if halted:
            self._settle(FitOutcome(error=HALTED, window_s=window_s))
            return
        self._submit("final", self._request(t, h, trigger_time_s, window_s, "final", position, section_heads))

    # ------------------------------------------------------------------ outcomes (the service's threads)
    def _ended(self, kind: str, request: FitRequest, fut) -> None:
        with self._lock:
            self._running.discard(fut)
            self._quick.discard(fut)
            halted = self._halted
        exc = fut.exception()
        if kind == "final":
            self._final_ended(request, fut, exc, halted)
            return
        if exc is None:
            self.emit("fit", {"result": fut.result(), "final": False, "window_s": request.window_s})
        else:
            log.debug("%s fit ended: %s: %s", kind, type(exc).__name__, exc)

    def _final_ended(self, request: FitRequest, fut, exc, halted: bool) -> None:
        window = request.window_s
        if exc is None:
            r = fut.result()
            with self._lock:
                latency = time.perf_counter() - self._closed_at
            self.emit("fit", {"result": r, "final": True, "window_s": window})
            self._settle(FitOutcome(r, latency_s=latency, window_s=window))
        elif isinstance(exc, FitCancelled) or halted:
            self._settle(FitOutcome(error=HALTED, window_s=window))
        elif isinstance(exc, FitWorkerDied) and request.label == "recorder-final":
            # the final fit is not lost with its process: it runs here
            self.message(f"fit process lost ({exc}): fitting in the recorder's process")
            with self._lock:
                proc, self._proc = self._proc, None
            if proc is not None:
                proc.close()
            self._submit("final", replace(request, label="recorder-final-here"), self._here)
        else:
            text = f"fit failed: {exc}" if isinstance(exc, FitFailed) else f"fit failed: {type(exc).__name__}: {exc}"
            if not isinstance(exc, FitFailed):
                log.debug("fit failed", exc_info=exc)
            if self._settle(FitOutcome(error=text, window_s=window)):
                self.message(text)

    def _settle(self, outcome: FitOutcome) -> bool:
        """The final outcome, once: the first one said wins (refuse is atomic with the fit's end)."""
        with self._lock:
            if self._outcome is not None:
                return False
            self._outcome = outcome
        self._done.set()
        if self._deliver is not None:
            self._deliver(outcome)
        return True

    # ------------------------------------------------------------------ the run's end (control thread)
    def refuse(self, why: str) -> None:
        """No final fit, and why (the run's summary and the CLI say it); nothing if the outcome is known."""
        if self._settle(FitOutcome(error=why)):
            self.message(why)

    def cancel(self) -> None:
        """Halt: every fit ends now (the fit process is killed); the final outcome is HALTED."""
        with self._lock:
            self._halted = True
            running = [f for f in self._running if hasattr(f, "cancel_fit")]
        for f in running:
            f.cancel_fit(kill=True)

    def close(self) -> None:
        """Give the worker process back (kept for the next run if idle; ended if a fit still runs)."""
        with self._lock:
            proc, self._proc = self._proc, None
        if proc is not None:
            proc.close()

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the final outcome; True when it is known (or no final fit was started)."""
        with self._lock:
            if not self._final_started and self._outcome is None:
                return True
        return self._done.wait(timeout)
