"""The run's phases, which commands can succeed in each, and the end statuses with their exit codes.

One phase model, owned by the engine, emitted as ``phase`` events, printed by ``velab record``
and written as ``phase`` events into the run file (docs/recording.md, "Phases")::

    disconnected -> connecting -> ready -> armed (baseline filling) -> triggerable
        -> recording (fit window counting down) -> [fitting] -> completed | completed-with-faults
    any active phase -> stopped | aborted | failed

End statuses (bluesky's words): *stop* ends cleanly and keeps the data (status ``stopped``);
*abort* cleans up and marks the run (``aborted``: operator, pressure ceiling, actuator fault,
armed timeout); *halt* stops now, without the online fit (``aborted``, reason "halted").
"""

from __future__ import annotations

from velab.errors import ExitCode

DISCONNECTED, CONNECTING, READY = "disconnected", "connecting", "ready"
ARMED, TRIGGERABLE, RECORDING, FITTING = "armed", "triggerable", "recording", "fitting"
COMPLETED, COMPLETED_WITH_FAULTS = "completed", "completed-with-faults"
STOPPED, ABORTED, FAILED = "stopped", "aborted", "failed"

END_PHASES = (COMPLETED, COMPLETED_WITH_FAULTS, STOPPED, ABORTED, FAILED)
RUN_PHASES = (ARMED, TRIGGERABLE, RECORDING)  # a run file is open and the actuator may move
PHASES = (DISCONNECTED, CONNECTING, READY, ARMED, TRIGGERABLE, RECORDING, FITTING) + END_PHASES
ACTIVE_PHASES = (CONNECTING,) + RUN_PHASES + (FITTING,)

COMMANDS = ("connect", "arm", "trigger", "stop", "abort", "halt", "reset_valve", "close")

# exit codes of `velab record` per end status (velab.errors.ExitCode, docs/cli.md); "refused" is a
# run that never started (interlock, readiness)
EXIT_CODES = {COMPLETED: ExitCode.OK, COMPLETED_WITH_FAULTS: ExitCode.COMPLETED_WITH_FAULTS, "refused": ExitCode.REFUSED,
              ABORTED: ExitCode.ABORTED, FAILED: ExitCode.FAILURE, STOPPED: ExitCode.INTERRUPTED}


def allowed_commands(phase: str, *, valve_open: bool | None = None, trigger_queued: bool = False) -> tuple[str, ...]:
    """The commands that can succeed now (the GUI enables exactly these buttons).

    ``arm`` needs the valve open: after a run closed it (``valve_open`` False) only
    ``reset_valve`` can make the next ``arm`` possible. A trigger queued during the baseline
    is not offered again.
    """
    if phase in (DISCONNECTED, READY) + END_PHASES:
        cmds = ["connect", "reset_valve", "close"]
        if valve_open is not False:
            cmds.insert(1, "arm")
        return tuple(cmds)
    if phase == CONNECTING:
        return ("close",)
    if phase == ARMED:
        return (() if trigger_queued else ("trigger",)) + ("stop", "abort", "halt", "close")
    if phase == TRIGGERABLE:
        return ("trigger", "stop", "abort", "halt", "close")
    if phase == RECORDING:
        return ("stop", "abort", "halt", "close")
    if phase == FITTING:
        return ("halt", "close")
    return ("close",)


def exit_code(status: str) -> int:
    return int(EXIT_CODES.get(status, ExitCode.FAILURE))


def worst_exit_code(codes) -> int:
    """A campaign's code: its most severe run's (ExitCode.worst)."""
    return int(ExitCode.worst(codes))
