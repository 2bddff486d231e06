"""The online fit: the recorded window -> the fitter, on its own thread, with intermediate fits.

``fit_record`` is the one thin call into the fitter (velab.fitting.prepare.fit_record, the
fit path ``velab fit`` and the GUI's re-fit take too); everything else here is scheduling: intermediate quick fits on the growing
window while the fitter is idle, cancelled when the final fit starts; the final fit as soon
as the window closes; the latency from the window closing to the result.
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np

from velab.config import Rig

log = logging.getLogger(__name__)
MIN_FIT_WINDOW_S = 2.0


class _Cancelled(Exception):
    pass


def fit_record(t_s: np.ndarray, head_m: np.ndarray, trigger_time_s: float, rig: Rig, *, models, window_s: float,
               method: str, sample_rate_hz: float, quick: bool = False, progress=None):
    """Fit a recorded head record (the run's axis, absolute head, from before the trigger) -> SweepResult.

    The one fit path (velab.fitting.prepare: steady head, window, anti-alias decimation to the fit
    rate), as ``velab fit`` of the run file takes it; ``quick`` = no polish, 2 starts (intermediate fits).
    """
    from velab.fitting.prepare import fit_record as fit_path  # scipy: only when a fit runs

    kw = {"polish": False, "starts": 2} if quick else {}
    return fit_path(t_s, head_m, trigger_time_s, rig, window_s, record_rate_hz=sample_rate_hz, models=list(models),
                    method=method, progress=progress, **kw)


class OnlineFit:
    """Runs fits of the recorded window; publishes ``fit`` events through ``emit``; thread-safe."""

    def __init__(self, rig: Rig, settings, sample_rate_hz: float, emit, message):
        self.rig = rig
        self.s = settings
        self.fs = sample_rate_hz
        self.emit = emit
        self.message = message
        self.result = None
        self.error = ""
        self.latency_s: float | None = None
        self.window_s: float | None = None
        self._final: threading.Thread | None = None
        self._busy = threading.Event()
        self._cancel_quick = threading.Event()
        self._cancel_all = threading.Event()
        self._closed_at: float | None = None

    @property
    def busy(self) -> bool:
        return self._busy.is_set()

    @property
    def final_started(self) -> bool:
        return self._final is not None

    def start(self, t: np.ndarray, h: np.ndarray, trigger_time_s: float, window_s: float, *, final: bool) -> None:
        """Start a fit of (t, h) over ``window_s`` after the trigger (a quick one is skipped while another runs)."""
        if final:
            if self._final is not None:
                return
            self._closed_at = time.perf_counter()
            self._cancel_quick.set()  # the final fit gets the CPU
        elif self._busy.is_set():
            return
        else:
            self._cancel_quick.clear()
        self._busy.set()
        th = threading.Thread(target=self._work, args=(t, h, trigger_time_s, window_s, final), daemon=True,
                              name="velab-recorder-fit" + ("" if final else "-quick"))
        if final:
            self._final = th
            self.window_s = window_s
        th.start()

    def refuse(self, why: str) -> None:
        """No final fit, and why (the run's summary and the CLI say it)."""
        if not self.error and self.result is None:
            self.error = why
            self.message(why)

    def _work(self, t, h, trigger_time_s, window_s, final) -> None:
        def progress(done, total, name):
            if self._cancel_all.is_set() or (not final and self._cancel_quick.is_set()):
                raise _Cancelled()

        try:
            r = fit_record(t, h, trigger_time_s, self.rig, models=self.s.fit_models, window_s=window_s,
                           method=self.s.fit_method, sample_rate_hz=self.fs, quick=not final, progress=progress)
            if final:
                self.result = r
                self.latency_s = time.perf_counter() - self._closed_at
            self.emit("fit", {"result": r, "final": final, "window_s": window_s})
        except _Cancelled:
            if final:
                self.error = "fit cancelled (halt)"
        except Exception as exc:  # noqa: BLE001 - reported as the run's fit error
            log.debug("fit failed", exc_info=True)
            if final:
                self.error = f"fit failed: {type(exc).__name__}: {exc}"
                self.message(self.error)
        finally:
            if final or not self._cancel_quick.is_set() or self._final is None:
                self._busy.clear()

    def cancel(self) -> None:
        self._cancel_all.set()

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the final fit; True when it is over (or never started)."""
        th = self._final
        if th is None:
            return True
        th.join(timeout)
        return not th.is_alive()
