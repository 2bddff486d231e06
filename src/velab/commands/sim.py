"""``velab sim``: run the whole simulated rig until Ctrl-C, printing each device's endpoint."""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "sim", help="run the simulated rig (Modbus ADC, flowmeter, valve actuator) on loopback and ptys",
        description="Start every simulated device of a sim config and serve it until Ctrl-C. "
                    "Binds 127.0.0.1 unless --host says otherwise.",
    )
    p.add_argument("--config", default="default", help="sim config name (configs/sim/<name>.toml) or path")
    p.add_argument("--host", default=None, help="address to bind (default: the config's, 127.0.0.1)")
    p.add_argument("--ephemeral", action="store_true", help="ephemeral ports, no pty links (ignore fixed ports)")
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds (default: Ctrl-C)")
    p.add_argument("--json", action="store_true",
                   help="print the endpoints as one JSON line on stdout (pid, endpoints, a bench config "
                        "reaching them), for scripts and tests")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from velab.simulators.bench import SimulatedBench

    sim = SimulatedBench.from_config(args.config, ephemeral=args.ephemeral, host=args.host)
    stop = threading.Event()
    previous = signal.signal(signal.SIGTERM, lambda *a: stop.set())
    try:
        sim.start()
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
    print("velab sim: stopped", file=sys.stderr)
    return 0


def _print_endpoints(sim, rig) -> None:
    print(f"velab sim: rig {rig.name}, material {sim.rig.material.name}, "
          f"Q0 = {rig.steady_flow_m3_s * 1e3:.2f} l/s, steady head {rig.steady_head_m:.2f} m")
    for e in sim.endpoints:
        extra = f" (link {e.link})" if e.link else ""
        unit = f" unit {e.unit}" if e.unit is not None else ""
        print(f"  {e.device:<14} {e.kind:<15} {e.transport:<11} {e.address}{extra}{unit}")
    print("Ctrl-C to stop.", flush=True)
