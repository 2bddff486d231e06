"""velab.recording.slow alone, one poll at a time (``poll()``), on fake devices: slow samples written,
a silent valve a fault said once, its link state readable from another thread, a FAULT ends the run."""

from __future__ import annotations

from types import SimpleNamespace

from stage_helpers import RecordingHooks
from velab.drivers.base import DeviceTimeout
from velab.drivers.valve import ValveState
from velab.recording.ops import Slow
from velab.recording.slow import SlowChannels


def status(state=ValveState.ARMED, pos=100.0, faults=()):
    return SimpleNamespace(state=state, position=SimpleNamespace(value=pos), faults=list(faults))


class Scripted:
    def __init__(self, replies):
        self.replies = list(replies)

    def next(self):
        r = self.replies.pop(0) if len(self.replies) > 1 else self.replies[0]
        if isinstance(r, BaseException):
            raise r
        return r


def make(valve_replies, flow=0.01, stall_s=10.0, triggered=False):
    rec, ops, seen = RecordingHooks(), [], []
    v = Scripted(valve_replies)
    valve = SimpleNamespace(read_status=v.next)
    fm = SimpleNamespace(read_flow=lambda: SimpleNamespace(value=flow, quality=SimpleNamespace(value="ok")))
    slow = SlowChannels(valve, "valve", fm, rec.hooks, ops.append, lambda: 1.5, lambda: triggered, stall_s,
                        on_valve=seen.append)
    return slow, rec, ops, seen


def test_a_poll_writes_the_valve_and_the_flow():
    slow, rec, ops, seen = make([status()])
    slow.poll()
    assert [(op.name, op.t) for op in ops] == [("valve_state", 1.5), ("valve_opening", 1.5), ("flow", 1.5)]
    assert all(isinstance(op, Slow) for op in ops) and len(seen) == 1
    assert [k for k, _ in rec.emitted] == ["valve", "device"] and slow.valve_link() == (True, "")


def test_a_silent_valve_is_one_fault_then_answers_again():
    slow, rec, _, _ = make([DeviceTimeout("no reply"), DeviceTimeout("no reply"), status()])
    slow.poll()
    slow.poll()
    assert slow.valve_link() == (False, "no reply")
    slow.poll()
    assert slow.valve_link()[0]
    assert [f[1] for f in rec.faults] == ["actuator does not answer: no reply", "answers again"]
    assert not rec.ends


def test_a_valve_silent_too_long_before_the_trigger_fails_the_run():
    slow, rec, _, _ = make([DeviceTimeout("no reply")], stall_s=0.0)
    slow.poll()
    slow.poll()
    assert rec.ends and rec.ends[0][0] == "failed" and "before the trigger" in rec.ends[0][1]


def test_an_actuator_fault_aborts_the_run():
    slow, rec, _, _ = make([status(ValveState.FAULT, 40.0, ["overtravel"])])
    slow.poll()
    assert rec.ends[0][0] == "aborted" and "overtravel" in rec.ends[0][1]


def test_a_held_valve_is_left_alone():
    slow, _, ops, seen = make([status()])
    slow.hold_valve(True)
    slow.poll()
    assert [op.name for op in ops] == ["flow"] and not seen
