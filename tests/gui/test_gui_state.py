"""What each phase enables (velab.gui.state, Qt-free): the table of docs/gui.md, from the engine's
allowed commands and the window's own commands in flight; the phase line and its countdowns."""

from __future__ import annotations

import pytest

from velab.gui.state import ControlState
from velab.recording import phases as P

OPEN = {"state": "IDLE", "position_pct": 100.0, "open": True}
CLOSED = {"state": "DONE", "position_pct": 0.0, "open": False}
FAULT = {"state": "FAULT", "position_pct": 40.0, "open": False}

# phase, valve, trigger queued -> the buttons enabled (docs/gui.md, "Phases and buttons")
TABLE = [
    (P.DISCONNECTED, None, False, {"connect", "arm", "reset_valve"}),
    (P.CONNECTING, None, False, set()),
    (P.READY, OPEN, False, {"connect", "arm", "reset_valve"}),
    (P.ARMED, OPEN, False, {"trigger", "stop", "abort"}),
    (P.ARMED, OPEN, True, {"stop", "abort"}),
    (P.TRIGGERABLE, OPEN, False, {"trigger", "stop", "abort"}),
    (P.RECORDING, CLOSED, False, {"stop", "abort"}),
    (P.FITTING, CLOSED, False, set()),
    (P.COMPLETED, CLOSED, False, {"connect", "arm", "reset_valve"}),  # Arm reopens the valve first
    (P.COMPLETED_WITH_FAULTS, CLOSED, False, {"connect", "arm", "reset_valve"}),
    (P.STOPPED, OPEN, False, {"connect", "arm", "reset_valve"}),
    (P.ABORTED, FAULT, False, {"connect", "reset_valve"}),  # an actuator FAULT: Reset valve first
    (P.FAILED, None, False, {"connect", "arm", "reset_valve"}),
]


def _state(phase, valve, queued=False, in_flight=(), data=None, progress=None):
    valve_open = None if valve is None else valve["open"]
    return ControlState(phase=phase, allowed=P.allowed_commands(phase, valve_open=valve_open, trigger_queued=queued),
                        data=dict(data or {}, **({"trigger_queued": True} if queued else {})),
                        progress=progress or {}, in_flight=tuple(in_flight), valve=valve)


@pytest.mark.parametrize("phase,valve,queued,enabled", TABLE)
def test_buttons_follow_the_engines_phase(phase, valve, queued, enabled):
    st = _state(phase, valve, queued)
    assert {b for b, on in st.controls().items() if on} == enabled
    assert st.indicator()[0] == phase  # the engine's word, as velab record prints it


@pytest.mark.parametrize("busy", ["setup", "connect", "settings", "reset", "arm"])
def test_a_command_in_flight_holds_every_button(busy):
    for phase, valve, queued, _ in TABLE:
        st = _state(phase, valve, queued, in_flight=(busy,))
        assert not any(st.controls().values()), (phase, busy)


def test_a_trigger_in_flight_is_not_offered_again_and_an_ending_run_takes_no_more_commands():
    st = _state(P.ARMED, OPEN, in_flight=("trigger",))
    assert {b for b, on in st.controls().items() if on} == {"stop", "abort"}
    st = _state(P.RECORDING, CLOSED, in_flight=("stop",))
    assert not any(st.controls().values())


def test_arm_after_a_run_reopens_the_valve_but_not_from_a_fault():
    assert _state(P.COMPLETED, CLOSED).reopen_before_arm
    assert not _state(P.COMPLETED, OPEN).reopen_before_arm
    assert not _state(P.ABORTED, FAULT).reopen_before_arm
    assert "Reset valve" in _state(P.ABORTED, FAULT).indicator()[1]


def test_countdowns_on_screen():
    data = {"baseline_s": 2.0, "remaining_s": 2.0, "armed_timeout_s": 300.0}
    st = _state(P.ARMED, OPEN, data=data, progress={"phase": P.ARMED, "what": "baseline", "remaining_s": 1.2})
    assert st.indicator()[1].startswith("baseline 1.2 s to go") and "disarms in 4:59" in st.indicator()[1]
    st = _state(P.ARMED, OPEN, queued=True, data=data,
                progress={"phase": P.ARMED, "what": "baseline", "remaining_s": 1.2})
    assert st.indicator()[1].startswith("Trigger queued: fires when the baseline is in, 1.2 s")
    st = _state(P.TRIGGERABLE, OPEN, data={"disarm_in_s": 298.0},
                progress={"phase": P.TRIGGERABLE, "what": "armed timeout", "remaining_s": 42.5})
    assert "disarms in 42.5 s" in st.indicator()[1] and st.disarm_in() == 42.5
    st = _state(P.RECORDING, CLOSED, data={"fit_window_s": 20.0, "remaining_s": 20.0},
                progress={"phase": P.RECORDING, "what": "fit window", "remaining_s": 12.34})
    assert st.indicator()[1].startswith("fit window 12.3 s to go")
    # a countdown of another phase is not shown
    st = _state(P.RECORDING, CLOSED, data={"fit_window_s": 20.0, "remaining_s": 20.0},
                progress={"phase": P.ARMED, "what": "baseline", "remaining_s": 0.5})
    assert st.indicator()[1].startswith("fit window 20.0 s to go")


def test_arm_not_offered_when_the_interlock_refuses():
    from velab.gui.state import ControlState
    from velab.recording import phases as P

    for phase in (P.READY, P.DISCONNECTED, P.COMPLETED):
        st = ControlState(phase=phase, allowed=P.allowed_commands(phase), refused="predicted peak EXCEEDS")
        assert not st.controls()["arm"], phase
        assert "interlock refuses" in st.indicator()[1].lower()
        assert ControlState(phase=phase, allowed=P.allowed_commands(phase)).controls()["arm"] == (
            "arm" in P.allowed_commands(phase))


def test_fitting_shown_while_the_final_fit_runs_beside_the_recording():
    from velab.gui.state import ControlState
    from velab.recording import phases as P

    run = {"duration_s": 30.0, "fit": True, "fit_window_s": 20.0, "final_fit": False}
    base = dict(phase=P.RECORDING, allowed=P.allowed_commands(P.RECORDING), data={"trigger_time_s": 2.0}, run=run)
    before = ControlState(**base, progress={"phase": P.RECORDING, "what": "fit window", "remaining_s": 5.0, "t_s": 17.0})
    assert before.indicator()[0] == P.RECORDING and "fit window 5.0 s to go" in before.indicator()[1]
    during = ControlState(**base, progress={"phase": P.RECORDING, "what": "fit window", "remaining_s": 0.0, "t_s": 23.8})
    phase, detail = during.indicator()
    assert phase == P.FITTING and "final fit of the 20 s window running" in detail and "ends in 8.2 s" in detail
    assert during.controls()["stop"] and during.controls()["abort"]  # the engine still records
    done = ControlState(**{**base, "run": {**run, "final_fit": True}},
                       progress={"phase": P.RECORDING, "what": "fit window", "remaining_s": 0.0, "t_s": 28.0})
    assert done.indicator() == (P.RECORDING, "final fit done; recording ends in 4.0 s (Stop keeps the run)")
    no_fit = ControlState(**{**base, "run": {**run, "fit": False}},
                         progress={"phase": P.RECORDING, "what": "fit window", "remaining_s": 0.0, "t_s": 28.0})
    assert no_fit.indicator()[0] == P.RECORDING
