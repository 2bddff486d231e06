"""velab.recording.trigger alone, on a scripted valve (no bus): each outcome of a TRIGGER named, and
the valve's safe state from each state it can be in (the recorder's and `velab valve close`'s)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from velab.drivers.base import DeviceTimeout, TriggerNotStarted, TriggerRefused, TriggerUnknown
from velab.drivers.valve import TriggerOutcome, TriggerResult, ValveState
from velab.recording.trigger import TriggerFailed, make_safe, readback_note, trigger_manoeuvre


class Valve:
    def __init__(self, trigger=None, states=(ValveState.ARMED,), abort_error=None):
        self._trigger, self.states, self.abort_error, self.calls = trigger, list(states), abort_error, []

    def trigger(self):
        self.calls.append("trigger")
        if isinstance(self._trigger, BaseException):
            raise self._trigger
        return self._trigger or TriggerOutcome(TriggerResult.STARTED)

    def read_status(self):
        self.calls.append("read_status")
        state = self.states.pop(0) if len(self.states) > 1 else self.states[0]
        return SimpleNamespace(state=state, position=SimpleNamespace(value=0.0 if state is ValveState.DONE else 100.0))

    def abort(self):
        self.calls.append("abort")
        if self.abort_error:
            raise self.abort_error


def test_a_started_trigger_is_its_outcome():
    out = trigger_manoeuvre(Valve())
    assert out.started and readback_note(out) is None


def test_a_lost_reply_read_back_as_started_is_noted():
    st = SimpleNamespace(state=ValveState.RUNNING, trigger_count=4)
    out = trigger_manoeuvre(Valve(TriggerOutcome(TriggerResult.STARTED, True, st, DeviceTimeout("no reply"))))
    assert readback_note(out) == ("TRIGGER reply lost (no reply); state read back: RUNNING, trigger count 4: "
                                  "the manoeuvre started")


@pytest.mark.parametrize("error, ask, words", [
    (TriggerNotStarted("valve: read back: not started"), True, "trigger not started"),
    (TriggerRefused("valve: TRIGGER refused", 4), True, "trigger not started"),
    (TriggerUnknown("valve: no read-back"), False, "trigger outcome unknown"),
    (DeviceTimeout("valve: no reply"), False, "trigger outcome unknown"),
])
def test_a_failed_trigger_names_its_outcome_and_how_to_make_the_valve_safe(error, ask, words):
    with pytest.raises(TriggerFailed) as info:
        trigger_manoeuvre(Valve(error), " (sent at about t = 0.100 s)")
    assert str(info.value).startswith(words + " (sent at about t = 0.100 s): ") and info.value.ask_valve is ask


@pytest.mark.parametrize("state, line", [
    (ValveState.ARMED, "actuator: armed manoeuvre cancelled (abort)"),
    (ValveState.RUNNING, "actuator: manoeuvre stopped where it is (abort)"),
    (ValveState.IDLE, "actuator: IDLE at 100.0 % open, at rest: the safe state already"),
    (ValveState.DONE, "actuator: DONE at 0.0 % open, at rest: the safe state already"),
])
def test_the_safe_state_asks_the_valve_first(state, line):
    v = Valve(states=[state])
    assert make_safe(v) == line
    assert v.calls == (["read_status", "abort"] if "abort" in line else ["read_status"])


def test_a_valve_that_does_not_answer_is_aborted_without_asking():
    v = Valve()
    assert make_safe(v, ask=False) == "actuator: abort commanded (state unknown)" and v.calls == ["abort"]


def test_a_stroke_that_ended_before_the_abort_is_at_rest_not_a_fault():
    v = Valve(states=[ValveState.RUNNING, ValveState.DONE], abort_error=DeviceTimeout("no running manoeuvre"))
    assert make_safe(v).startswith("actuator: DONE before the abort arrived")


def test_a_valve_that_cannot_be_made_safe_raises():
    v = Valve(states=[ValveState.RUNNING, ValveState.RUNNING], abort_error=DeviceTimeout("no reply"))
    with pytest.raises(DeviceTimeout):
        make_safe(v)
