"""``velab valve open|close|status --config BENCH``: the valve actuator between runs.

``open`` resets the actuator (the valve reopens; a FAULT is cleared) and waits until it is idle
and open; ``close`` runs the closing manoeuvre only if the surge interlock allows it (the same
limits as a run: the Joukowsky surge over the steady head, with margin, within the transducer's
range and the pipe's rating); ``status`` prints the state. Exit codes as ``velab record``: 0 done,
2 bad arguments or configuration, 3 refused by the interlock, 5 the actuator does not answer.
"""

from __future__ import annotations

import sys
import time

from velab.commands.common import add_json_option, float_range, write_json
from velab.errors import VelabError


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "valve", help="open (reset), close (with the interlock) or read the valve actuator of a bench",
        description="Drive the bench's valve actuator between runs. 'open' resets it (the valve reopens), "
                    "'close' runs the closing manoeuvre if the surge interlock allows it, 'status' reads it.",
        epilog="exit codes: 0 done, 2 bad arguments/config, 3 refused by the interlock, 5 actuator failure")
    p.add_argument("action", choices=("open", "close", "status"))
    p.add_argument("--config", required=True, metavar="BENCH", help="bench config (configs/benches/<name>.toml or a path)")
    p.add_argument("--rig", default="perugia", help="rig config for the interlock (perugia)")
    p.add_argument("--beta", type=float_range(0, 1e4, lo_open=True, units="1/s"), default=None, help="closing manoeuvre beta, 1/s (default: the rig's)")
    p.add_argument("--gamma", type=float_range(-100, 100), default=None, help="closing manoeuvre gamma (default: the rig's)")
    p.add_argument("--end-position", type=float_range(0, 100, hi_open=True, units="%"), default=0.0, help="final opening, %% (0)")
    p.add_argument("--surge-margin", type=float_range(0, 10), default=0.1, help="interlock margin on the surge (0.1)")
    add_json_option(p)
    p.set_defaults(func=run_command)


def _status_dict(name, st) -> dict:
    from velab.recording.slow import valve_event

    return valve_event(name, st) | {"trigger_count": st.trigger_count}


def run_command(args) -> int:
    # here, not at the top: `velab --help` never loads numpy (velab.recording) or the drivers
    from velab.config import load_rig
    from velab.drivers.base import DeviceError, ProfileError
    from velab.drivers.bench import load_bench, open_device
    from velab.drivers.valve import ValveState
    from velab.errors import SafetyError
    from velab.recording.devices import reopen_valve, resolve_roles
    from velab.recording.safety import predict_surge
    from velab.recording.settings import RecordSettings
    from velab.recording.trigger import TriggerFailed, make_safe, readback_note, trigger_manoeuvre
    from velab.recording.types import DEVICE_ERRORS, DeviceFailure

    try:
        bench = load_bench(args.config)
    except ProfileError as exc:
        raise VelabError(str(exc)) from None
    rig = load_rig(args.rig)
    name = resolve_roles(bench)["valve"]
    s = None
    if args.action == "close":  # the interlock first: nothing is asked of the actuator if it refuses
        s = RecordSettings(beta_per_s=args.beta, gamma=args.gamma, end_position_pct=args.end_position,
                           surge_margin=args.surge_margin, fit=False)
        pred = predict_surge(rig, s)
        if not pred.allowed:
            raise SafetyError(pred.message)
    try:
        valve = open_device(bench.devices[name])
    except (DeviceError, OSError) as exc:
        raise DeviceFailure(f"{name}: cannot connect: {exc}") from None
    try:
        if args.action == "open":
            st = reopen_valve(valve, time.sleep)
        elif args.action == "close":
            st = valve.read_status()
            if st.state is not ValveState.IDLE:
                raise SafetyError(f"{name}: not idle ({st.state.name}, {st.position.value:.1f} % open): "
                                  "'velab valve open' first")
            m = rig.manoeuvre
            valve.set_manoeuvre(args.beta or m.beta_per_s, m.gamma if args.gamma is None else args.gamma,
                                args.end_position)
            valve.arm()
            try:
                note = readback_note(trigger_manoeuvre(valve))
            except TriggerFailed as exc:  # the valve to its safe state, as a run's failed trigger
                try:
                    line = make_safe(valve, exc.ask_valve)
                except DEVICE_ERRORS as safe_exc:
                    line = f"could not be commanded to its safe state: {safe_exc}"
                raise DeviceFailure(f"{name}: {exc}" + (f"; {line}" if line else "")) from None
            if note:
                print(f"{name}: warning: {note}", file=sys.stderr)
            st = valve.wait_for({ValveState.DONE}, timeout_s=30.0)
        else:
            st = valve.read_status()
    except DeviceError as exc:
        raise DeviceFailure(f"{name}: {exc}") from None
    finally:
        valve.close()
    d = _status_dict(name, st)
    if args.json:
        write_json(d)
    else:
        faults = f", faults: {', '.join(d['faults'])}" if d["faults"] else ""
        print(f"{name}: {d['state']}, {d['position_pct']:.1f} % open ({'open' if d['open'] else 'not open'}){faults}")
    return 0
