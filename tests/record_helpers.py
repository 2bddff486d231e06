"""Shared by the recorder's fault tests: run a recording against the simulated rig with a deadline,
and catch what escapes any engine thread (a traceback somewhere)."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import logging
import threading
import time
from types import SimpleNamespace

import pytest

from velab.errors import VelabError
from velab.recording import Recorder, RecordSettings
from velab.simulators.bench import SimulatedBench
from velab.simulators.clock import make_clock

# The clock of recordings through the Modbus ADC where the test needs every sample: its ring is read 125 registers a
# request, and at the fast clock (12 x) a 2 kHz x 3 channel ring asked the in-process client and simulator for ~580
# requests a second (48 on the real bench); under two suites at once the host fell behind and samples were lost
# (the run rightly flagged). At 4 x: ~190 a second, and the ring holds 3 x more host time.
MODBUS_ADC_CLOCK = "scaled:4"


def rate_clock(rate_hz: float) -> str:
    """The clock of a simulated recording at ``rate_hz`` through the streaming ADC: the fast clock (12 x) up to
    2 kHz; 4 x above. At 10 kHz and 12 x the in-process simulator sends 120,000 samples a second of host time
    (10,000 on the real bench); under two suites at once the reader fell 50,745 samples behind and lost them, and
    STOP's reply waited behind a second of frames ('no reply to STOP within 1 s'). At 4 x: 40,000 a second."""
    return "fast" if rate_hz <= 2000.0 else MODBUS_ADC_CLOCK  # (the same 4 x)


DEADLINE_S = 40.0  # a scenario that has not ended by then hangs (the documented bounds are seconds)
CWF, FAILED, ABORTED = "completed-with-faults", "failed", "aborted"


@pytest.fixture
def thread_errors():
    """Exceptions escaping any thread, and ERROR logs of the engine (a traceback somewhere)."""
    seen = []
    old = threading.excepthook
    threading.excepthook = lambda a: seen.append(f"{a.thread.name}: {a.exc_type.__name__}: {a.exc_value}")

    class H(logging.Handler):
        def emit(self, record):
            seen.append(record.getMessage())

    h = H(level=logging.ERROR)
    logging.getLogger("velab").addHandler(h)
    yield seen
    logging.getLogger("velab").removeHandler(h)
    threading.excepthook = old


def fast_sim(config="default", clock: str = "fast") -> SimulatedBench:
    """The simulated rig of a sim config (name, path or dict) on the fast clock (or ``clock``: "scaled:K"),
    ephemeral endpoints."""
    if isinstance(config, dict):
        sim = SimulatedBench(config, ephemeral=True, clock=make_clock(clock))
    else:
        sim = SimulatedBench.from_config(config, ephemeral=True, clock=make_clock(clock))
    return sim.start()


def short_settings(out_dir, **kw) -> RecordSettings:
    base = dict(duration_s=3.0, pretrigger_s=0.5, fit=False, out_dir=out_dir, stall_timeout_s=1.5)
    return RecordSettings(**(base | kw))


def recorder(sim, settings, source: str | None = None, prefer=None) -> Recorder:
    bench = sim.bench(prefer=prefer)
    if source:
        bench = dataclasses.replace(bench, recorder=bench.recorder | {"pressure_source": source})
    return Recorder(bench, sim.rig.rig, settings, sim=sim, owns_sim=True)


@dataclasses.dataclass
class Outcome:
    summary: object  # RunSummary, or None if the run could not start
    error: Exception | None  # what rec.run() raised (refused, could not arm)
    elapsed_s: float
    valve_state: str  # the simulated actuator's state when the run had ended
    triggers: int  # TRIGGERs the simulated actuator carried out


def run_bounded(rec: Recorder, faults: list | None = None, deadline_s: float = DEADLINE_S) -> Outcome:
    """rec.run() on a thread with a deadline; ``faults`` collects the fault events. Closes the recorder
    (and the simulator it owns) within the deadline."""
    if faults is not None:
        rec.add_listener(lambda ev: faults.append(ev.data) if ev.kind == "fault" else None)
    box: dict = {}

    def run():
        try:
            box["summary"] = rec.run()
        except VelabError as exc:
            box["error"] = exc

    t0 = time.monotonic()
    th = threading.Thread(target=run, daemon=True)
    th.start()
    th.join(deadline_s)
    elapsed = time.monotonic() - t0
    hung = th.is_alive()
    phase = rec.phase
    rig = rec.sim.rig
    valve_state, triggers = rig.state().name, rig.trigger_count
    closer = threading.Thread(target=rec.close, daemon=True)
    closer.start()
    closer.join(deadline_s)
    assert not hung, f"no outcome within {deadline_s} s (phase {phase})"
    assert not closer.is_alive(), "close() did not return"
    return Outcome(box.get("summary"), box.get("error"), elapsed, valve_state, triggers)


def assert_halted_fit(summary, halt_s: float, busy: list) -> None:
    """A halt during a fit: the run aborted "halted" with no fit and a named fit error, the halt
    returned within seconds, and the fit processes that were computing are gone (killed, not left
    computing) within 5 s."""
    assert summary.status == "aborted" and "halted" in summary.reason
    assert summary.fit is None and "halted" in summary.fit_error
    assert halt_s < 6.0
    end = time.monotonic() + 5
    while any(w.alive for w in busy) and time.monotonic() < end:
        time.sleep(0.02)
    assert busy, "no fit process was seen computing the final fit before the halt"
    assert not any(w.alive for w in busy), "a fit process still alive 5 s after the halt"


def cli(argv) -> SimpleNamespace:
    """``velab ARGV`` in this process, as the entry point runs it (velab.cli.main): ``returncode``, ``stdout`` and
    ``stderr``, as subprocess.run gives them. For a command whose outcome, not its process, is what a test checks
    (a refusal decided before anything is recorded, an offline fit or listing of a file); ``velab record`` and
    ``velab fit`` as processes of their own record, fit, refuse and are killed in tests/recording/test_record.py,
    test_record_process.py, test_record_faults.py, tests/runfiles/test_runfile_atomic.py and
    tests/commands/test_record_arguments.py (each child costs 1-4 s of CPU in imports alone)."""
    from velab.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        try:
            code = main([str(a) for a in argv])
        except SystemExit as exc:
            code = exc.code
    return SimpleNamespace(returncode=code, stdout=out.getvalue(), stderr=err.getvalue())
