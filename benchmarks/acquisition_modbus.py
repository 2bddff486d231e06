"""Modbus buffered ADC throughput over TCP against the simulated rig (real time), against raw block reads.

    python benchmarks/acquisition_modbus.py [--rate 2000] [--channels 2] [--seconds 5] [--poll 0.02]
                                            [--baseline-seconds 2]

The simulated module runs in a separate process (as a real module would be a
separate box), so the CPU time reported is the acquisition client's alone.

For each rate, against the same server:

* **driver**: ModbusADC.read_buffer() every ``--poll`` s for ``--seconds`` s (the
  sample counter, the new samples in blocks of <= 125 registers, conversion to
  engineering units and quality, gap accounting). Prints samples/s, lost samples,
  requests/s, CPU time per second of data and per sample;
* **raw block reads** (the baseline, the transport's ceiling): velab's own
  ModbusClient issuing the same ring-buffer block reads (FC3, read holding, as the
  driver; per_block = 125 // channels samples = per_block * channels registers,
  walking the ring window) back to back for ``--baseline-seconds`` s, with none of
  the driver's bookkeeping (no counter reads, no conversion, no gap accounting).
  Prints the maximum samples/s the transport + server deliver and the CPU per sample
  (its "CPU s per s of data" = CPU per sample x the rate: what raw reads alone would cost).

Ratios printed on the driver row: "% of max" = driver samples/s over the raw
maximum samples/s (the share of the transport's capacity the acquisition uses;
100 / that = the headroom factor), and "CPU x raw" = the driver's CPU per sample
over the raw reads' CPU per sample (the driver's overhead factor).

Exits 1 if the sustained rate at 2 kHz is below the requested one or samples were lost.
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


def raw_block_reads(bus, ring_address: int, capacity: int, channels: int, seconds: float) -> dict:
    """The baseline: back-to-back ring block reads with the bare ModbusClient, nothing else."""
    from velab.drivers.modbus import MAX_READ_REGISTERS

    per_block = MAX_READ_REGISTERS // channels
    n_req0 = bus.stats.requests
    samples = 0
    k = 0
    cpu0, wall0 = time.process_time(), time.perf_counter()
    while time.perf_counter() - wall0 < seconds:
        slot = k % capacity
        m = min(per_block, capacity - slot)
        bus.read_holding(ring_address + slot * channels, m * channels)
        samples += m
        k += m
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    return {"samples_per_s": samples / wall, "requests": bus.stats.requests - n_req0, "wall_s": wall,
            "registers": per_block * channels, "cpu_us_per_sample": 1e6 * cpu / samples}


def run(rate: int, channels: int, seconds: float, poll_s: float, baseline_s: float = 2.0) -> dict:
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
            "cpu_us_per_sample": 1e6 * cpu / adc.stats.samples if adc.stats.samples else float("nan"),
        }
        # the baseline: same server, same connection (velab's ModbusClient), same block reads, no driver
        cap, nch = int(adc.read_value("buffer_capacity")), int(adc.read_value("buffer_channels"))
        res["raw"] = raw_block_reads(adc.bus, adc.ring_address, cap, nch, baseline_s)
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
    ap.add_argument("--baseline-seconds", type=float, default=2.0,
                    help="duration of the raw block-read baseline per rate (s, default 2)")
    a = ap.parse_args(argv)
    ok = True
    print(f"Modbus buffered ADC over TCP (loopback), {a.channels} ch, simulated module in another process; "
          f"driver polls every {a.poll * 1e3:g} ms for {a.seconds:g} s")
    print(f"baseline 'raw reads': back-to-back {(125 // a.channels) * a.channels}-register FC3 ring reads by "
          f"ModbusClient, same server, {a.baseline_seconds:g} s (no counter reads, conversion or gap accounting)")
    print(f"{'rate Hz':>8} {'ch':>3} {'reader':<10} {'samples/s':>10} {'lost':>6} {'overruns':>8} {'req/s':>7} "
          f"{'CPU s per s of data':>20} {'CPU us/sample':>14} {'% of max':>9} {'CPU x raw':>10}")
    for rate in a.rate:
        r = run(rate, a.channels, a.seconds, a.poll, a.baseline_seconds)
        b = r["raw"]
        share = r["samples_per_s"] / b["samples_per_s"]
        cpu_x = r["cpu_us_per_sample"] / b["cpu_us_per_sample"]
        print(f"{r['rate_hz']:>8} {r['channels']:>3} {'driver':<10} {r['samples_per_s']:>10.0f} {r['lost']:>6} "
              f"{r['overruns']:>8} {r['requests'] / r['wall_s']:>7.0f} {r['cpu_s_per_s_of_data']:>20.4f} "
              f"{r['cpu_us_per_sample']:>14.2f} {share:>9.1%} {cpu_x:>9.1f}x")
        print(f"{'':>8} {r['channels']:>3} {'raw reads':<10} {b['samples_per_s']:>10.0f} {'-':>6} {'-':>8} "
              f"{b['requests'] / b['wall_s']:>7.0f} {b['cpu_us_per_sample'] * 1e-6 * rate:>20.4f} "
              f"{b['cpu_us_per_sample']:>14.2f} {'(baseline)':>20}")
        if rate == 2000:
            ok &= r["lost"] == 0 and r["samples_per_s"] >= 0.98 * rate
    print("% of max: driver samples/s / raw-read max samples/s (share of the transport's capacity used); "
          "CPU x raw: driver CPU per sample / raw-read CPU per sample")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
