"""The manoeuvre's trigger and the valve's safe state, each with its outcomes named: one function for
the recorder (velab.recording.run) and for ``velab valve close``.

A TRIGGER is sent once and never retried blindly (the driver reads the valve back after a lost
reply). Three outcomes: started (perhaps after a read-back: ``readback_note`` says so); not
started or refused (the valve is still armed, nothing moved: the safe state asks the valve and
aborts it); unknown (no read-back: the valve may be closing: ABORT without asking first).
"""

from __future__ import annotations

from velab.drivers.base import TriggerNotStarted, TriggerUnknown
from velab.drivers.valve import TriggerOutcome, ValveState
from velab.recording.types import DEVICE_ERRORS, DeviceFailure

AT_REST = (ValveState.DONE, ValveState.HOLDING, ValveState.ABORTED, ValveState.IDLE)


class TriggerFailed(DeviceFailure):
    """The manoeuvre did not (or may not) start: ``ask_valve`` False when the valve's state is unknown
    (its safe state is then commanded without reading it first)."""

    def __init__(self, message: str, ask_valve: bool):
        super().__init__(message)
        self.ask_valve = ask_valve


def trigger_manoeuvre(valve, when: str = "") -> TriggerOutcome:
    """TRIGGER ``valve`` once; its outcome (started) or TriggerFailed naming why not. ``when``: where
    the trigger was sent, for the message (e.g. " (sent at about t = 1.234 s)")."""
    try:
        return valve.trigger()
    except TriggerNotStarted as exc:  # also TriggerRefused: the valve is still armed, nothing moved
        raise TriggerFailed(f"trigger not started{when}: {exc}", ask_valve=True) from None
    except (TriggerUnknown,) + DEVICE_ERRORS as exc:  # the valve may be closing
        raise TriggerFailed(f"trigger outcome unknown{when}: {exc}", ask_valve=False) from None


def readback_note(out: TriggerOutcome) -> str | None:
    """A started trigger whose reply was lost: what the read-back said (a protocol fault), else None."""
    if not out.readback:
        return None
    st = out.status
    return (f"TRIGGER reply lost ({out.lost_reply}); state read back: {st.state.name}, trigger count "
            f"{st.trigger_count}: the manoeuvre started")


def make_safe(valve, ask: bool = True) -> str | None:
    """Command the valve to its safe state: an armed manoeuvre cancelled, a running one stopped where it
    is (ABORT). ``ask`` False: ABORT without reading the state first (it did not answer). Returns the
    line for the run's log (at rest too: the check's outcome is part of the record); raises a device error if
    the valve cannot be commanded."""
    st = valve.read_status() if ask else None
    state = st.state if st is not None else None
    if state not in (ValveState.ARMED, ValveState.RUNNING, None):
        return f"actuator: {state.name} at {float(st.position.value):.1f} % open, at rest: the safe state already"
    if state is ValveState.RUNNING and not getattr(valve, "can_stop", lambda: True)():
        # a fired actuator (velab.drivers.fired_valve) runs its stroke to its end: nothing to command
        return f"actuator: a fired stroke runs to its end (at {float(st.position.value):.1f} % open): it cannot be stopped"
    try:
        valve.abort()
    except DEVICE_ERRORS as exc:
        # a stroke that ended between the status read and the abort is refused ("no running
        # manoeuvre"): the valve is at rest, which is the safe state; anything else is a fault
        after = valve.read_status().state if state is not None else None
        if after not in AT_REST:
            raise
        return f"actuator: {after.name} before the abort arrived ({exc}): at rest"
    return {ValveState.ARMED: "actuator: armed manoeuvre cancelled (abort)",
            ValveState.RUNNING: "actuator: manoeuvre stopped where it is (abort)",
            None: "actuator: abort commanded (state unknown)"}[state]
