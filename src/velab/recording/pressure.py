"""The pressure source: a streaming ADC or a buffered Modbus ADC -> SampleBlocks with per-sample quality.

One class for both kinds: ``look()`` (a short pressure reading before anything is armed),
``start(on_block)`` (its own acquisition thread), ``stop()`` (bounded). Every block goes to
``on_block(block, pressure_codes, valve_codes)`` with the plausibility codes of
``velab.recording.safety.SensorCheck``. Failures end the run through ``hooks.request_end``:
a fatal driver error at once, a source that delivers nothing for ``stall_timeout_s`` (wall
seconds: a silent, frozen or vanished device, a reconnection that takes too long) as well.
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np

from velab.drivers.base import DeviceError, DeviceTimeout, pressure_to_head_m
from velab.recording.safety import SensorCheck
from velab.recording.types import DEVICE_ERRORS, DeviceFailure

log = logging.getLogger(__name__)


class PressureSource:
    def __init__(self, name: str, kind: str, driver, clock=None):
        self.name = name
        self.kind = kind
        self.adc = driver
        self.clock = clock
        self.streaming = kind == "streaming_adc"
        self.fs: float | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.outcome = ""  # how the acquisition thread ended: "stopped", "failed: ..."
        self.pressure_channel, self.valve_channel = self._channels()

    # ---------------------------------------------------------------- channels
    def _channels(self) -> tuple[str, str | None]:
        """(pressure channel, valve-position channel or None), by units."""
        adc = self.adc
        if self.streaming:
            chans = [(c.name, c.calibration.units) for c in adc.profile.channels]
            enabled = list(adc.profile.enabled)
        else:
            chans = [(c.name, c.calibration.units) for c in adc.channels]
            enabled = [c[0] for c in chans]
        p = next((n for n, u in chans if u == "Pa" and n in enabled), None)
        v = next((n for n, u in chans if u == "%" and n in enabled), None)
        if p is None:
            raise DeviceFailure(f"{self.name}: no pressure channel (units Pa) is acquired")
        return p, v

    def rate_range(self) -> tuple[float, float]:
        """The sample rates this source accepts (Hz)."""
        if self.streaming:
            from velab.drivers.streaming_adc import RATE_MAX_HZ, RATE_MIN_HZ

            return float(RATE_MIN_HZ), float(RATE_MAX_HZ)
        spec = self.adc.profile.reg("sample_rate")
        return float(spec.min if spec.min is not None else 1.0), float(spec.max if spec.max is not None else 1e4)

    def calibration(self) -> dict:
        if self.streaming:
            from dataclasses import asdict

            return {c.name: asdict(c.calibration) | {"range": c.range, "input": c.index} for c in self.adc.profile.channels}
        from dataclasses import asdict

        return {c.name: asdict(c.calibration) | {"type_code": c.type_code, "input": c.index} for c in self.adc.channels}

    def _block_samples(self, fs: float) -> int:
        from velab.drivers.streaming_adc import MAX_BLOCK, auto_block

        scale = getattr(self.clock, "scale", 1.0) if self.clock is not None else 1.0
        return int(min(MAX_BLOCK, max(auto_block(fs, 2), auto_block(fs * scale, 2))))

    # ---------------------------------------------------------------- before arming
    def look(self, fs: float) -> tuple[float, str]:
        """A short look at the pressure before anything is armed: (mean head, worst quality)."""
        adc, pch = self.adc, self.pressure_channel
        try:
            if self.streaming:
                adc.configure(fs, [pch], self._block_samples(fs))
                adc.start()
                vals, q = [], "ok"
                try:
                    need = max(10, int(0.05 * fs))
                    deadline = time.monotonic() + 5.0
                    while sum(v.size for v in vals) < need and time.monotonic() < deadline:
                        b = adc.get_block(timeout=2.0)
                        vals.append(b.head_m(pch))
                        codes = SensorCheck(None).codes(b.raw[:, 0], b.signal[:, 0], b.values[:, 0])
                        if b.quality[0].value != "ok" or codes.any():
                            q = b.quality[0].value if b.quality[0].value != "ok" else "implausible (out of 3.8-20.5 mA)"
                finally:
                    adc.stop()
                h = np.concatenate(vals) if vals else np.array([np.nan])
                return float(np.nanmean(h)) if np.isfinite(h).any() else float("nan"), q
            r = adc.read_pressure(pch)
            return float(pressure_to_head_m(r.value, adc.density_kg_m3)), r.quality.value
        except DEVICE_ERRORS as exc:
            raise DeviceFailure(f"{self.name}: pressure check failed: {exc}") from None

    # ---------------------------------------------------------------- acquisition
    def start(self, fs: float, stuck_after_s: float, stall_timeout_s: float, on_block, hooks) -> float:
        """Start the device and the acquisition thread; returns the device's actual rate."""
        adc = self.adc
        chans = [self.pressure_channel] + ([self.valve_channel] if self.valve_channel else [])
        if self.streaming:
            cfg = adc.configure(fs, chans, self._block_samples(fs))
            adc.start(wait_when_full=True)
            self.fs = float(cfg.rate_hz) if abs(cfg.rate_hz - fs) > 1e-6 * fs else float(fs)
        else:
            adc.stop_buffer()
            adc.configure_buffer(int(fs), len(chans))
            adc.start_buffer()
            self.fs = float(adc.sample_rate_hz or fs)
        stuck = max(20, int(round(stuck_after_s * self.fs)))
        self._checks = (SensorCheck(stuck), SensorCheck(None))
        self._stop.clear()
        self.outcome = ""
        self._thread = threading.Thread(target=self._loop, args=(on_block, hooks, stall_timeout_s), daemon=True,
                                        name="velab-recorder-acquisition")
        self._thread.start()
        return self.fs

    def _codes(self, b):
        out = []
        for ch, check in zip((self.pressure_channel, self.valve_channel), self._checks):
            if ch is None or ch not in b.channels:
                out.append(None)
                continue
            j = b.channels.index(ch)
            dq = None if b.sample_quality is None else b.sample_quality[:, j]
            cal = self.adc.profile.channel(ch).calibration if self.streaming else self.adc.channel(ch).calibration
            units = getattr(cal, "signal_units", "mA")
            out.append(check.codes(b.raw[:, j], b.signal[:, j], b.values[:, j], units, dq))
        return out

    def _loop(self, on_block, hooks, stall_timeout_s: float) -> None:
        adc = self.adc
        last_data = time.monotonic()
        last_error: str = ""
        try:
            while not self._stop.is_set():
                try:
                    if self.streaming:
                        try:
                            blocks = [adc.get_block(timeout=0.2)] + adc.get_blocks()
                        except DeviceTimeout:
                            if adc.error is not None:  # the reader gave up: fatal
                                raise adc.error from None
                            blocks = []
                    else:
                        b = adc.read_buffer()
                        blocks = [b] if b.n or b.lost_before else []
                        if last_error:
                            hooks.fault("pressure", f"answers again after: {last_error}", "no_response")
                            last_error = ""
                except DEVICE_ERRORS as exc:
                    if self.streaming:
                        raise DeviceError(str(exc)) from None
                    # the Modbus ADC's ring keeps the samples: retry until the stall timeout
                    if not last_error:
                        hooks.fault("pressure", f"{exc} (retrying; the module's buffer keeps the samples)",
                                    "no_response")
                    last_error = str(exc)
                    blocks = []
                for b in blocks:
                    p_codes, v_codes = self._codes(b)
                    on_block(b, p_codes, v_codes)
                    last_data = time.monotonic()
                    if self._stop.is_set():
                        break
                if not blocks:
                    if time.monotonic() - last_data > stall_timeout_s:
                        why = f"no pressure samples for {stall_timeout_s:g} s"
                        if last_error:
                            why += f" (last error: {last_error})"
                        elif self.streaming and adc.error is None:
                            why += " (device silent, frozen or reconnecting)"
                        raise DeviceError(why)
                    if not self.streaming:
                        time.sleep(0.01)
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
            if self.streaming:
                self.adc.stop()
            else:
                self.adc.stop_buffer()
        except Exception as exc:  # noqa: BLE001 - a dead device cannot be stopped; say so once
            problem = f"pressure ADC stop: {exc}"
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(5.0)
            if self._thread.is_alive():
                problem = (problem + "; " if problem else "") + "acquisition thread did not end within 5 s"
        return problem
