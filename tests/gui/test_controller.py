"""velab.gui.controller alone, on a fake recorder (no engine, no devices): events become signals through
one table, samples are batched in order, the state is the engine's one snapshot plus the window's
commands in flight."""

from __future__ import annotations

from concurrent.futures import Future
from types import MappingProxyType

import numpy as np
import pytest

from velab.recording import phases as P
from velab.recording.events import EventQueue
from velab.recording.types import EngineSnapshot, RecorderEvent

pytestmark = pytest.mark.gui


class FakeRecorder:
    def __init__(self):
        self.events = EventQueue()
        self.snapshot = EngineSnapshot(P.READY, MappingProxyType({}), P.allowed_commands(P.READY))
        self.trigger_future = Future()

    def trigger(self):
        return self.trigger_future

    def emit(self, kind, data):
        self.events.offer(RecorderEvent(kind, 0.0, data))


@pytest.fixture
def ctl(qapp):
    from velab.gui.controller import RecorderController

    c = RecorderController(lambda **kw: FakeRecorder())
    c.timer.stop()  # the test drains by hand
    c.recorder = FakeRecorder()
    yield c
    c.recorder = None
    c.close()


def test_events_become_signals_and_samples_are_batched_in_order(ctl):
    ctl.budget_s = 60.0  # one tick takes them all however slow the host (the budget: the test below)
    got = []
    ctl.samples.connect(lambda t, h, v, lost: got.append(("samples", t.tolist(), lost)))
    ctl.message.connect(lambda text, level: got.append(("message", text)))
    ctl.trigger_time.connect(lambda t, measured: got.append(("trigger", t, measured)))
    ctl.valve.connect(lambda d: got.append(("valve", d["state"])))
    rec = ctl.recorder
    for i in range(2):
        rec.emit("samples", {"time_s": np.array([float(i)]), "head_m": np.array([30.0]), "lost": i})
    rec.emit("message", "hello")
    rec.emit("samples", {"time_s": np.array([2.0]), "head_m": np.array([30.0]), "valve_position": np.array([99.0]),
                         "lost": 0})
    rec.emit("trigger", {"trigger_time_s": 0.5, "measured": True})
    rec.emit("valve", {"state": "IDLE", "open": True})
    rec.emit("unknown-kind", None)  # a kind this window does not know: ignored
    ctl.drain()
    assert got == [("samples", [0.0, 1.0], 1), ("message", "hello"), ("samples", [2.0], 0), ("trigger", 0.5, True),
                   ("valve", "IDLE")]
    assert ctl.valve_info == {"state": "IDLE", "open": True} and ctl.events_seen == 7


def test_events_past_the_ticks_time_budget_wait_for_the_next_tick(ctl):
    got = []
    ctl.message.connect(lambda text, level: got.append(text))
    for i in range(3):
        ctl.recorder.emit("message", f"m{i}")
    ctl.budget_s = 0.0  # the budget spent before the first event: the GUI thread is handed back at once
    ctl.drain()
    assert got == [] and ctl.events_seen == 0
    ctl.budget_s = 60.0
    ctl.drain()
    assert got == ["m0", "m1", "m2"] and ctl.events_seen == 3


def test_the_state_is_the_engines_snapshot_plus_commands_in_flight(ctl):
    rec = ctl.recorder
    rec.snapshot = EngineSnapshot(P.TRIGGERABLE, MappingProxyType({"path": "a.h5"}), P.allowed_commands(P.TRIGGERABLE))
    phases = []
    ctl.phase_changed.connect(phases.append)
    ctl.drain()
    assert ctl.state.phase == P.TRIGGERABLE and ctl.state.data == {"path": "a.h5"} and ctl.can("trigger")
    ctl.trigger()
    assert ctl.state.in_flight == ("trigger",)
    rec.trigger_future.set_result(0.25)
    fired = []
    ctl.triggered.connect(fired.append)
    ctl.drain()
    assert fired == [0.25] and ctl.state.in_flight == () and phases == [P.TRIGGERABLE]


def test_a_cancelled_queued_trigger_is_said_once(ctl):
    rec = ctl.recorder
    rec.snapshot = EngineSnapshot(P.ARMED, MappingProxyType({}), P.allowed_commands(P.ARMED))
    ctl.drain()
    cancelled, failed = [], []
    ctl.trigger_cancelled.connect(cancelled.append)
    ctl.command_failed.connect(lambda name, exc: failed.append(name))
    ctl.trigger()
    rec.trigger_future.set_exception(RuntimeError("trigger cancelled: the run ended"))
    ctl.drain()
    assert cancelled and not failed
