"""What the window shows and enables, derived from the engine's phase alone (Qt-free, pure).

The engine (velab.recording) owns the one phase model and says, with every phase, which
commands can succeed now (``allowed``). The window adds only what it knows itself: which
of its own commands are still in flight. ``controls()`` turns the two into the enabled
state of each button; ``indicator()`` into the phase line and its countdown. The phase
names are the engine's, the ones ``velab record`` prints (docs/gui.md, "Phases and buttons").
"""

from __future__ import annotations

from dataclasses import dataclass, field

from velab.recording import phases as P

BUTTONS = ("connect", "arm", "trigger", "stop", "abort", "reset_valve")
# the window's own commands that hold every button until they settle (a Recorder being made or
# connected, the form's settings being turned into RecordSettings, the valve reopening, an arm)
BLOCKING = ("setup", "connect", "settings", "reset", "arm")
ENDING = ("stop", "abort")

COLORS = {P.DISCONNECTED: "#eeeeee", P.CONNECTING: "#e8f1fb", P.READY: "#e4f4e0", P.ARMED: "#fff0c2",
          P.TRIGGERABLE: "#ffe08a", P.RECORDING: "#ffd9a8", P.FITTING: "#dbe9ff", P.COMPLETED: "#d8f0d2",
          P.COMPLETED_WITH_FAULTS: "#fbe7c6", P.STOPPED: "#eeeeee", P.ABORTED: "#f9d0cd", P.FAILED: "#f9d0cd"}


@dataclass(frozen=True)
class ControlState:
    """One snapshot: the engine's phase, its data and allowed commands, the window's commands in flight."""

    phase: str = P.DISCONNECTED
    allowed: tuple = ()
    data: dict = field(default_factory=dict)  # the phase's data (path, baseline_s, armed_timeout_s, ...)
    progress: dict = field(default_factory=dict)  # the last countdown {what, remaining_s, t_s}
    in_flight: tuple = ()  # names of the window's commands not settled yet
    valve: dict | None = None  # the engine's last valve status {state, position_pct, open, faults}
    run: dict = field(default_factory=dict)  # the armed run as the window asked for it: duration_s, fit,
    # fit_window_s, and final_fit once the final fit's result is in
    refused: str = ""  # the interlock refuses the form's settings (why): Arm would be refused, so it is not offered

    @property
    def valve_closed(self) -> bool:
        return self.valve is not None and not self.valve.get("open", True)

    @property
    def valve_fault(self) -> bool:
        return self.valve is not None and self.valve.get("state") == "FAULT"

    @property
    def reopen_before_arm(self) -> bool:
        """Arm after a run that closed the valve: the window reopens it first (not from an actuator FAULT)."""
        return ("arm" not in self.allowed and "reset_valve" in self.allowed and self.valve_closed
                and not self.valve_fault)

    @property
    def trigger_queued(self) -> bool:
        return bool(self.data.get("trigger_queued")) and self.phase == P.ARMED

    def controls(self) -> dict[str, bool]:
        """Each button is enabled exactly when its action can succeed now."""
        allowed = set(self.allowed)
        busy = any(n in BLOCKING for n in self.in_flight)
        ending = any(n in ENDING for n in self.in_flight)
        return {
            "connect": not busy and "connect" in allowed,
            "arm": not busy and not self.refused and ("arm" in allowed or self.reopen_before_arm),
            "trigger": not busy and not ending and "trigger" in allowed and "trigger" not in self.in_flight,
            "stop": not busy and not ending and "stop" in allowed,
            "abort": not busy and not ending and "abort" in allowed,
            "reset_valve": not busy and "reset_valve" in allowed,
        }

    def countdown(self, what: str) -> float | None:
        """The last remaining time the engine published for ``what`` in this phase (None: none yet)."""
        pr = self.progress
        if pr.get("phase") == self.phase and pr.get("what") == what:
            return float(pr.get("remaining_s", 0.0))
        return None

    def disarm_in(self) -> float | None:
        """Seconds until an armed rig disarms itself (armed: from the baseline countdown)."""
        if self.phase == P.TRIGGERABLE:
            left = self.countdown("armed timeout")
            return left if left is not None else self.data.get("disarm_in_s")
        if self.phase == P.ARMED:
            timeout, base = self.data.get("armed_timeout_s"), self.data.get("baseline_s")
            left = self.countdown("baseline")
            if timeout is None or base is None:
                return None
            return float(timeout) - (float(base) - (left if left is not None else float(base)))
        return None

    def recording_left(self) -> float | None:
        """Seconds of recording still to come (the armed duration after the trigger), None if unknown."""
        dur, trig, now = self.run.get("duration_s"), self.data.get("trigger_time_s"), self.progress.get("t_s")
        if not all(isinstance(x, (int, float)) for x in (dur, trig, now)) or self.progress.get("phase") != P.RECORDING:
            return None
        return max(0.0, float(trig) + float(dur) - float(now))

    def indicator(self) -> tuple[str, str]:
        """(phase, detail): the phase word as ``velab record`` prints it and what it means now."""
        ph, d = self.phase, self.data
        if "setup" in self.in_flight:
            return P.CONNECTING, "starting the bench and opening the devices…"
        if ph == P.DISCONNECTED:
            why = d.get("reason")
            tail = (" The interlock refuses these settings: change the manoeuvre or the margin to arm."
                    if self.refused else "")
            return ph, (f"{why}. " if why else "") + "Connect opens the devices (Arm connects first)." + tail
        if ph == P.CONNECTING:
            return ph, "opening and reading the devices…"
        if ph == P.READY or ph in P.END_PHASES:
            if ph in P.END_PHASES:
                head = d.get("reason") or ("run completed" if ph == P.COMPLETED else "")
            else:
                head = "every device answered"
            if "arm" in self.in_flight or "settings" in self.in_flight:
                tail = "arming: readiness checks (steady flow and head), run file, actuator…"
            elif "reset" in self.in_flight:
                tail = "reopening the valve (actuator reset, 1 s for the flow to settle)…"
            elif self.valve_fault:
                tail = "actuator FAULT: Reset valve before the next run"
            elif self.refused:
                tail = "the interlock refuses these settings: change the manoeuvre or the margin to arm"
            elif self.reopen_before_arm:
                tail = "valve closed: Arm reopens it first (or Reset valve)"
            else:
                tail = "press Arm for the next run" if ph in P.END_PHASES else "press Arm"
            return ph, "; ".join(x for x in (head, tail) if x)
        if ph == P.ARMED:
            base = self.countdown("baseline")
            base = base if base is not None else d.get("remaining_s", d.get("baseline_s", 0.0))
            dis = self.disarm_in()
            tail = f" · disarms in {_mmss(dis)} without a trigger" if dis is not None else ""
            if self.trigger_queued or "trigger" in self.in_flight:
                return ph, f"Trigger queued: fires when the baseline is in, {base:.1f} s{tail}"
            return ph, f"baseline {base:.1f} s to go (Trigger now is queued){tail}"
        if ph == P.TRIGGERABLE:
            dis = self.disarm_in()
            return ph, "baseline in: press Trigger" + (f" · disarms in {_mmss(dis)} without a trigger"
                                                       if dis is not None else "")
        if ph == P.RECORDING:
            left = self.countdown("fit window")
            left = left if left is not None else d.get("remaining_s", d.get("fit_window_s"))
            rest = self.recording_left()
            tail = f"recording ends in {rest:.1f} s" if rest is not None else "recording goes on"
            if left is not None and left <= 0.0:  # the window is in: the final fit runs while the rest records
                if self.run.get("fit", True) and not self.run.get("final_fit"):
                    return P.FITTING, f"final fit of the {self.run.get('fit_window_s') or 0:g} s window running; " \
                                      f"{tail} (Stop keeps the run and its fit)"
                done = "final fit done; " if self.run.get("final_fit") else ""
                return ph, f"{done}{tail} (Stop keeps the run)"
            return ph, (f"fit window {left:.1f} s to go" if left is not None else "manoeuvre commanded") + \
                " (Stop keeps the run; the fit needs the whole window)"
        if ph == P.FITTING:
            return ph, f"final fit running (run {d.get('status', '')}); its result appears on the Fit page".replace(" ()", "")
        return ph, ""


def _mmss(seconds: float | None) -> str:
    if seconds is None:
        return "—"
    s = max(0.0, float(seconds))
    return f"{s:.1f} s" if s < 60 else f"{int(s // 60)}:{int(s % 60):02d}"
