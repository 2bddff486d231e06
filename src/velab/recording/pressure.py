"""The pressure stage: a pressure source (velab.drivers.pressure_source: either ADC, one verb set) on
its own acquisition thread -> SampleBlocks with per-sample quality -> the time line.

``look()`` (a short pressure reading before anything is armed), ``start(on_block)`` (the
acquisition thread), ``stop()`` (bounded). The stage acquires the pressure channels it is given
(``pressure``: every transducer's, the valve's first; default the source's first pressure channel)
and the valve position. Every block goes to ``on_block(block, codes)`` with the driver's per-sample
quality codes of each of its channels, by channel name (``SampleBlock.sample_quality``: the one
source of per-sample quality; NE43 limits, open loop, NaN, stuck counts are the driver's, from its
profile). Failures end the run through
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
    def __init__(self, source: PressureSource, pressure: tuple[str, ...] | None = None):
        self.source = source
        self.name = source.name
        self.fs: float | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.outcome = ""  # how the acquisition thread ended: "stopped", "failed: ..."
        p, v = source.channels()
        if p is None:
            raise DeviceFailure(f"{self.name}: no pressure channel (units Pa) is acquired")
        # the transducers' channels, the valve's first (velab.recording.transducers)
        self.pressure = tuple(pressure) if pressure else (p,)
        self.pressure_channel, self.valve_channel = self.pressure[0], v

    def rate_range(self) -> tuple[float, float]:
        """The sample rates this source accepts (Hz)."""
        return self.source.rate_range()

    def calibration(self) -> dict:
        return self.source.calibration()

    # ---------------------------------------------------------------- before arming
    def look(self, fs: float) -> dict[str, tuple[float, str]]:
        """A short look at every pressure channel before anything is armed: {channel: (mean head, worst quality)}."""
        try:
            return self.source.spot_heads(fs, self.pressure)
        except DEVICE_ERRORS as exc:
            raise DeviceFailure(f"{self.name}: pressure check failed: {exc}") from None

    # ---------------------------------------------------------------- acquisition
    def configure(self, fs: float) -> float:
        """Set the device up for a run at ``fs``; returns the rate it will sample at (a streaming ADC's clock
        divider makes 7000 Hz 6997.9 Hz): the run's time axis, file and fit are built on that rate."""
        self.fs = float(self.source.configure(fs, self.pressure))
        return self.fs

    def start(self, stall_timeout_s: float, on_block, hooks) -> float:
        """Start the configured device and the acquisition thread; returns the rate the device reports once
        it runs (the buffered ADC's read back)."""
        self.fs = self.source.start()
        self._stop.clear()
        self.outcome = ""
        self._thread = threading.Thread(target=self._loop, args=(on_block, hooks, stall_timeout_s), daemon=True,
                                        name="velab-recorder-acquisition")
        self._thread.start()
        return self.fs

    def _codes(self, b) -> dict:
        return {ch: sample_codes(b, ch) for ch in self.pressure + (self.valve_channel,) if ch and ch in b.channels}

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
                    on_block(b, self._codes(b))
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
