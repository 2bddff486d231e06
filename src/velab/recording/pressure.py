"""The pressure stage: a pressure source (velab.drivers.pressure_source: either ADC, one verb set) on
its own acquisition thread -> SampleBlocks with per-sample quality -> the time line.

``look()`` (a short pressure reading before anything is armed), ``start(on_block)`` (the
acquisition thread), ``stop()`` (bounded). Every block goes to ``on_block(block, pressure_codes,
valve_codes)`` with the driver's per-sample quality codes of those channels
(``SampleBlock.sample_quality``: the one source of per-sample quality; NE43 limits, open loop,
NaN, stuck counts are the driver's, from its profile). Failures end the run through
``hooks.request_end``: a fatal source error at once; a transient one (a polled ADC's failed poll:
its ring keeps the samples) is a fault, retried; a source that delivers nothing for
``stall_timeout_s`` (wall seconds: a silent, frozen or vanished device, a reconnection that takes
too long) ends it as well.
"""

from __future__ import annotations

import logging
import threading
import time

from velab.drivers.base import DeviceError
from velab.drivers.pressure_source import PressureSource, sample_codes
from velab.recording.types import DEVICE_ERRORS, DeviceFailure

log = logging.getLogger(__name__)


class PressureStage:
    def __init__(self, source: PressureSource):
        self.source = source
        self.name = source.name
        self.fs: float | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.outcome = ""  # how the acquisition thread ended: "stopped", "failed: ..."
        p, v = source.channels()
        if p is None:
            raise DeviceFailure(f"{self.name}: no pressure channel (units Pa) is acquired")
        self.pressure_channel, self.valve_channel = p, v

    def rate_range(self) -> tuple[float, float]:
        """The sample rates this source accepts (Hz)."""
        return self.source.rate_range()

    def calibration(self) -> dict:
        return self.source.calibration()

    # ---------------------------------------------------------------- before arming
    def look(self, fs: float) -> tuple[float, str]:
        """A short look at the pressure before anything is armed: (mean head, worst quality)."""
        try:
            return self.source.spot_head(fs)
        except DEVICE_ERRORS as exc:
            raise DeviceFailure(f"{self.name}: pressure check failed: {exc}") from None

    # ---------------------------------------------------------------- acquisition
    def start(self, fs: float, stall_timeout_s: float, on_block, hooks) -> float:
        """Start the device and the acquisition thread; returns the device's actual rate."""
        self.source.configure(fs)
        self.fs = self.source.start()
        self._stop.clear()
        self.outcome = ""
        self._thread = threading.Thread(target=self._loop, args=(on_block, hooks, stall_timeout_s), daemon=True,
                                        name="velab-recorder-acquisition")
        self._thread.start()
        return self.fs

    def _codes(self, b):
        return [None if ch is None or ch not in b.channels else sample_codes(b, ch)
                for ch in (self.pressure_channel, self.valve_channel)]

    def _loop(self, on_block, hooks, stall_timeout_s: float) -> None:
        last_data = time.monotonic()
        last_error: str = ""
        try:
            while not self._stop.is_set():
                r = self.source.read_blocks()  # a fatal error raises (DeviceError)
                if r.error:
                    if not last_error:
                        hooks.fault("pressure", f"{r.error} ({r.note})", "no_response")
                    last_error = r.error
                elif last_error:
                    hooks.fault("pressure", f"answers again after: {last_error}", "no_response")
                    last_error = ""
                for b in r.blocks:
                    p_codes, v_codes = self._codes(b)
                    on_block(b, p_codes, v_codes)
                    last_data = time.monotonic()
                    if self._stop.is_set():
                        break
                if not r.blocks and time.monotonic() - last_data > stall_timeout_s:
                    why = f"no pressure samples for {stall_timeout_s:g} s"
                    why += f" (last error: {last_error})" if last_error else self.source.stall_hint()
                    raise DeviceError(why)
            self.outcome = "stopped"
        except DeviceError as exc:
            if self._stop.is_set():
                self.outcome = "stopped"
                return
            msg = str(exc)
            if msg.startswith(f"{self.name}: "):
                msg = msg[len(self.name) + 2:]
            self.outcome = f"failed: {msg}"
            hooks.fault("pressure", f"acquisition failed: {msg}", "no_response")
            hooks.request_end("failed", f"{self.name} (pressure source): acquisition failed: {msg}")
        except Exception as exc:  # noqa: BLE001 - a bug: still end the run, and say so
            log.exception("acquisition thread")
            self.outcome = f"failed: {type(exc).__name__}: {exc}"
            hooks.request_end("failed", f"acquisition error: {type(exc).__name__}: {exc}")

    def stop(self) -> str:
        """Stop the acquisition thread and the device (bounded); returns a fault message or ''."""
        self._stop.set()
        problem = ""
        try:
            self.source.stop()
        except Exception as exc:  # noqa: BLE001 - a dead device cannot be stopped; say so once
            problem = f"pressure ADC stop: {exc}"
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(5.0)
            if self._thread.is_alive():
                problem = (problem + "; " if problem else "") + "acquisition thread did not end within 5 s"
        return problem
