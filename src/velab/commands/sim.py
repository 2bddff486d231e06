"""``velab sim``: run the whole simulated rig until Ctrl-C, printing each device's endpoint."""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import threading

from velab.configpath import DEFAULT_SIM
from velab.commands.common import float_range
from velab.errors import UnavailableError

log = logging.getLogger("velab.sim")

# What a remote peer can do with each simulated device kind (printed with --allow-remote).
EXPOSED = {
    "valve_actuator": "valve control: position set-points and the closing manoeuvre (Modbus writes)",
    "modbus_adc": "pressure and valve-position readings, acquisition start/stop (Modbus writes)",
    "streaming_adc": "pressure and valve-position streams, acquisition commands",
    "flowmeter": "flow readings, totaliser and settings (Modbus writes)",
    "dataq": "pressure and valve-position streams, acquisition commands, the digital line that fires the valve",
    "labjack": "pressure and valve-position streams, Modbus writes, the digital line that fires the valve",
    "fired_valve": "the valve, fired through its DAQ's digital line",
}


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "sim", help="run the simulated rig (Modbus ADC, flowmeter, valve actuator) on loopback and ptys",
        description="Start every simulated device of a sim config and serve it until Ctrl-C. "
                    "Binds 127.0.0.1 unless --host says otherwise; an address that is not loopback "
                    "(e.g. 0.0.0.0) puts valve control on the network and needs --allow-remote.",
    )
    p.add_argument("--config", default=DEFAULT_SIM, help=f"sim config name (sim/<name>.toml on the config path) or "
                                                         f"path (default {DEFAULT_SIM})")
    p.add_argument("--host", default=None, help="address to bind (default: the config's, 127.0.0.1)")
    p.add_argument("--allow-remote", action="store_true",
                   help="allow a --host that is not a loopback address (anyone who reaches it can move the valve)")
    p.add_argument("--ephemeral", action="store_true", help="ephemeral ports, no pty links (ignore fixed ports)")
    p.add_argument("--duration", type=float_range(0, 1e7, lo_open=True, units="s"), default=None,
                   help="stop after this many seconds (default: Ctrl-C)")
    p.add_argument("--json", action="store_true",
                   help="print the endpoints as one JSON line on stdout (pid, endpoints, a bench config "
                        "reaching them), for scripts and tests")
    p.set_defaults(func=run)


def exposure_notice(sim) -> str:
    """What a simulator bound beyond loopback exposes, device by device (one paragraph, for stderr)."""
    lines = [f"velab sim: WARNING: serving on {sim.host!r}, which is not a loopback address: anyone who can "
             f"reach this machine on the ports below can use the simulated devices:"]
    for name, h in sim.handles.items():
        kind = getattr(getattr(h, "device", None), "kind", None) or sim.config.get("devices", {}).get(name, {}).get("kind")
        lines.append(f"  {name:<14} {EXPOSED.get(kind, kind or 'device')}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from velab.simulators.bench import SimulatedBench, is_loopback_host

    sim = SimulatedBench.from_config(args.config, ephemeral=args.ephemeral, host=args.host,
                                     allow_remote=args.allow_remote)
    remote = not is_loopback_host(sim.host)
    if remote:
        print(exposure_notice(sim), file=sys.stderr, flush=True)
    stop = threading.Event()
    previous = signal.signal(signal.SIGTERM, lambda *a: stop.set())
    try:
        try:
            sim.start()
        except (OSError, RuntimeError) as exc:  # a fixed port already taken, no ptys
            raise UnavailableError(f"cannot start the simulated rig: {exc} (another `velab sim`? try --ephemeral)") from None
        rig = sim.rig.rig
        if args.json:
            print(json.dumps({"pid": os.getpid(), **sim.describe()}), flush=True)
        else:
            _print_endpoints(sim, rig)
        try:
            stop.wait(args.duration)
        except KeyboardInterrupt:
            pass
    finally:
        signal.signal(signal.SIGTERM, previous)
        sim.stop()
    log.info("velab sim: stopped")
    return 0


def _print_endpoints(sim, rig) -> None:
    print(f"velab sim: rig {rig.name}, material {sim.rig.material.name}, "
          f"Q0 = {rig.steady_flow_m3_s * 1e3:.2f} l/s, steady head {rig.steady_head_m:.2f} m")
    for e in sim.endpoints:
        extra = f" (link {e.link})" if e.link else ""
        unit = f" unit {e.unit}" if e.unit is not None else ""
        print(f"  {e.device:<14} {e.kind:<15} {e.transport:<11} {e.address}{extra}{unit}")
    print("Ctrl-C to stop.", flush=True)
