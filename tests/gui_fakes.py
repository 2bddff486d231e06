"""A stand-in for velab.recording.Recorder with the same contract (events queue, Future commands),
used to test the GUI's wiring without devices. The real engine is tested in test_gui_run.py."""

from __future__ import annotations

import queue
import threading
import time
from concurrent.futures import Future
from dataclasses import dataclass, field

import numpy as np

from velab.errors import SafetyError


@dataclass(frozen=True)
class Ev:
    kind: str
    time_s: float
    data: object


@dataclass(frozen=True)
class Pred:
    steady_head_m: float = 30.0
    surge_m: float = 40.0
    peak_head_m: float = 70.0
    peak_pressure_pa: float = 7.0e5
    limit_pa: float = 10e5
    limiting: str = "pipe rating"
    allowed: bool = True
    message: str = ""


@dataclass(frozen=True)
class Status:
    name: str
    ok: bool
    message: str = ""


@dataclass(frozen=True)
class Summary:
    path: str
    status: str
    reason: str = ""
    n_samples: int = 0
    lost_samples: int = 0
    peak_head_m: float = float("nan")
    fit: object = None
    best_model: str | None = None
    wave_speed_m_s: float | None = None


@dataclass
class FakeRecorder:
    settings: dict
    refuse_beta: float = 50.0
    block_s: float = 0.02
    events: queue.Queue = field(default_factory=queue.Queue)
    phase: str = "disconnected"

    def __post_init__(self):
        self.rate = float(self.settings.get("sample_rate_hz", 1000.0))
        self._stop = threading.Event()
        self._triggered_at = None
        self._thread = None
        self.n = 0

    def _done(self, value=None, exc=None) -> Future:
        f = Future()
        f.set_exception(exc) if exc else f.set_result(value)
        return f

    def _phase(self, p):
        self.phase = p
        self.events.put(Ev("phase", time.time(), p))

    def predict_surge(self, beta_per_s=None, gamma=None):
        beta = beta_per_s or 10.0
        ok = beta <= self.refuse_beta
        return Pred(allowed=ok, message="" if ok else f"closure rate {beta:g} 1/s: peak over the pipe rating")

    def connect(self):
        f = Future()

        def work():
            time.sleep(0.05)
            self._phase("ready")
            self.events.put(Ev("device", time.time(), {"pressure_adc.head": _R(30.0, "m"), "flowmeter.flow": _R(1.2, "l/s")}))
            f.set_result([Status("pressure_adc", True), Status("flowmeter", True), Status("valve", True)])
        threading.Thread(target=work, daemon=True).start()
        return f

    def arm(self):
        beta = self.settings.get("beta_per_s") or 10.0
        if beta > self.refuse_beta:
            return self._done(exc=SafetyError(f"closure rate {beta:g} 1/s: predicted peak over the pipe rating"))
        self._phase("triggerable")
        self._thread = threading.Thread(target=self._acquire, daemon=True)
        self._thread.start()
        return self._done("runs/fake.h5")

    def _acquire(self):
        t = -float(self.settings.get("pretrigger_s", 0.5))
        dur = float(self.settings.get("duration_s", 1.0))
        k = max(1, int(self.rate * self.block_s))
        next_t = time.perf_counter()
        while not self._stop.is_set():
            tt = t + np.arange(k) / self.rate
            head = 30.0 + np.where(tt > 0, 40 * np.exp(-tt) * np.cos(2 * np.pi * 2 * tt), 0.0)
            valve = np.where(tt > 0, np.maximum(0, 100 - 400 * tt), 100.0)
            self.events.put(Ev("samples", time.time(), {"time_s": tt, "head_m": head, "valve_position": valve, "lost": 0}))
            self.n += k
            t += k / self.rate
            if t >= dur:
                break
            if self.phase == "triggerable" and t >= 0:  # wait at the trigger until triggered
                while self._triggered_at is None and not self._stop.is_set():
                    time.sleep(0.005)
                self._phase("recording")
            next_t += self.block_s
            time.sleep(max(0.0, next_t - time.perf_counter()))
        status = "aborted" if self._stop.is_set() else "completed"
        self._phase("completed" if status == "completed" else "aborted")
        self.events.put(Ev("done", time.time(), Summary("runs/fake.h5", status, n_samples=self.n, peak_head_m=70.0)))

    def trigger(self):
        self._triggered_at = time.time()
        return self._done(0.0)

    def stop(self):
        self._stop.set()
        return self._done(None)

    def abort(self, reason=""):
        self._stop.set()
        return self._done(None)

    def inject_fault(self, device, message):
        self.events.put(Ev("fault", time.time(), {"device": device, "message": message}))

    def close(self):
        self._stop.set()


@dataclass(frozen=True)
class _R:
    value: float
    units: str
    timestamp_s: float = field(default_factory=time.time)
    quality: str = "ok"
