"""Modbus buffered ADC throughput over TCP against the simulated rig (real time).

    python benchmarks/acquisition_modbus.py [--rate 2000] [--channels 2] [--seconds 5] [--poll 0.02]

The simulated module runs in a separate process (as a real module would be a
separate box), so the CPU time reported is the acquisition client's alone.
Prints samples/s, lost samples and CPU time per second of data; exits 1 if the
sustained rate is below the requested one or samples were lost.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import sys
import time


def serve(rate: int, channels: int, q, stop) -> None:
    from velab.simulators.bench import SimulatedBench

    cfg = {"rig": "perugia", "material": "A", "devices": {"adc": {
        "kind": "modbus_adc", "sample_rate_hz": rate, "buffer_channels": channels, "endpoints": [{"transport": "tcp"}]}}}
    with SimulatedBench(cfg, ephemeral=True) as sim:
        q.put(sim.endpoint("adc").port)
        stop.wait()


def run(rate: int, channels: int, seconds: float, poll_s: float) -> dict:
    from velab.drivers.modbus import BusSettings, open_bus
    from velab.drivers.modbus_adc import ModbusADC

    ctx = mp.get_context("spawn")
    q, stop = ctx.Queue(), ctx.Event()
    proc = ctx.Process(target=serve, args=(rate, channels, q, stop), daemon=True)
    proc.start()
    try:
        port = q.get(timeout=30)
        adc = ModbusADC(open_bus(BusSettings(transport="tcp", port=port, unit=1, timeout_s=0.5, retries=1)))
        adc.start_buffer()
        cpu0, wall0 = time.process_time(), time.perf_counter()
        n_req0 = adc.bus.stats.requests
        while time.perf_counter() - wall0 < seconds:
            adc.read_buffer()
            time.sleep(poll_s)
        adc.read_buffer()
        wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
        data_s = adc.stats.samples / rate
        res = {
            "rate_hz": rate, "channels": channels, "wall_s": wall, "samples": adc.stats.samples,
            "samples_per_s": adc.stats.samples / wall, "lost": adc.stats.lost, "overruns": adc.stats.overruns,
            "requests": adc.bus.stats.requests - n_req0, "cpu_s_per_s_of_data": cpu / data_s if data_s else float("nan"),
        }
        adc.close()
        return res
    finally:
        stop.set()
        proc.join(5)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rate", type=int, nargs="+", default=[2000, 5000, 10000])
    ap.add_argument("--channels", type=int, default=2)
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--poll", type=float, default=0.02, help="sleep between buffer polls (s)")
    a = ap.parse_args(argv)
    ok = True
    print(f"{'rate Hz':>8} {'ch':>3} {'samples/s':>10} {'lost':>6} {'overruns':>8} {'req/s':>7} {'CPU s per s of data':>20}")
    for rate in a.rate:
        r = run(rate, a.channels, a.seconds, a.poll)
        print(f"{r['rate_hz']:>8} {r['channels']:>3} {r['samples_per_s']:>10.0f} {r['lost']:>6} {r['overruns']:>8} "
              f"{r['requests'] / r['wall_s']:>7.0f} {r['cpu_s_per_s_of_data']:>20.4f}")
        if rate == 2000:
            ok &= r["lost"] == 0 and r["samples_per_s"] >= 0.98 * rate
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
