"""Acquisition benchmark: can the streaming ADC driver keep up?

Runs the SADC-4 simulator in a separate process (fast mode: it streams as fast
as the driver reads, its device clock advancing by exactly 1/fs per sample) and
the driver in this process, reading through its reader thread and bounded queue
like the recorder will. For each case it prints the simulated duration, the
samples/s sustained, the lost samples (sequence gaps + queue overflow, must be
0) and the driver's CPU time per second of data (< 1 means it would keep up in
real time on one core).

    python benchmarks/acquisition.py                 # 10 kHz x1, 10 kHz x4 (60 s each), 50 kHz x4
    python benchmarks/acquisition.py --seconds 10 --transport pty

If benchmarks/acquisition_modbus.py exists (the Modbus ADC benchmark), it is run
afterwards so one script prints both.
"""

from __future__ import annotations

import argparse
import os
import resource
import runpy
import subprocess
import sys
import time
from pathlib import Path

from velab.drivers.streaming_adc import StreamingADC, default_profile

CASES = [  # (rate Hz, channels, headroom case?)
    (10_000, 1, False),
    (10_000, 4, False),
    (50_000, 4, True),
]
CHANNELS = ["pressure", "valve_position", "spare_2", "spare_3"]


def start_simulator(transport: str) -> tuple[subprocess.Popen, str]:
    arg = ["--pty"] if transport == "pty" else ["--tcp", "0"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "velab.simulators.streaming_adc", *arg, "--fast"],
        stdout=subprocess.PIPE, text=True,
    )
    url = proc.stdout.readline().strip()
    if not url:
        proc.kill()
        raise SystemExit("simulator did not start")
    return proc, url


def run_case(rate: float, nch: int, seconds: float, transport: str) -> dict:
    proc, url = start_simulator(transport)
    try:
        prof = default_profile(queue_blocks=20_000, data_timeout_s=5.0, reconnect=False)
        adc = StreamingADC(url, prof)
        adc.open()
        cfg = adc.configure(rate, CHANNELS[:nch])
        target = int(rate * seconds)
        got = 0
        cpu0, wall0 = time.process_time(), time.perf_counter()
        adc.start(wait_when_full=True)  # fast mode outruns real time: let back-pressure pace the device
        while got < target:
            got += adc.get_block(timeout=10).n
        stats = adc.stop()
        for b in adc.get_blocks():  # frames parsed while stopping
            got += b.n
        wall = time.perf_counter() - wall0
        cpu = time.process_time() - cpu0
        adc.close()
    finally:
        proc.terminate()
        proc.wait(5)
    sim_cpu = resource.getrusage(resource.RUSAGE_CHILDREN)
    data_s = stats.samples / cfg.rate_hz
    return dict(
        rate=cfg.rate_hz, nch=nch, block=cfg.block_samples, samples=stats.samples, data_s=data_s,
        wall=wall, sps=stats.samples / wall, values_ps=stats.samples * nch / wall,
        lost=stats.lost + stats.queue_dropped + stats.lost_estimated, crc=stats.crc_errors,
        cpu_per_s=cpu / data_s, speedup=data_s / wall, sim_cpu=sim_cpu.ru_utime + sim_cpu.ru_stime,
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="simulated seconds per case (default 60)")
    ap.add_argument("--transport", choices=["tcp", "pty"], default="tcp")
    ap.add_argument("--no-modbus", action="store_true", help="skip benchmarks/acquisition_modbus.py")
    args = ap.parse_args(argv)

    print(f"Streaming ADC (SADC-4) over {'socket://127.0.0.1' if args.transport == 'tcp' else 'pty'}, "
          f"simulator in a subprocess (fast mode), {os.cpu_count()} cores")
    print(f"{'case':<22}{'data s':>8}{'wall s':>8}{'x real':>8}{'samples/s':>12}{'values/s':>12}"
          f"{'lost':>7}{'CPU s/s data':>14}")
    ok = True
    for rate, nch, headroom in CASES:
        r = run_case(rate, nch, args.seconds, args.transport)
        name = f"{rate / 1000:g} kHz x {nch} ch" + (" (headroom)" if headroom else "")
        print(f"{name:<22}{r['data_s']:8.1f}{r['wall']:8.2f}{r['speedup']:8.1f}{r['sps']:12,.0f}"
              f"{r['values_ps']:12,.0f}{r['lost']:>7d}{r['cpu_per_s']:14.4f}")
        ok &= r["lost"] == 0 and r["data_s"] >= args.seconds
    print("PASS: zero lost samples in every case" if ok else "FAIL: samples lost or run too short")

    modbus = Path(__file__).with_name("acquisition_modbus.py")
    if modbus.exists() and not args.no_modbus:
        print()
        sys.stdout.flush()
        saved = sys.argv
        try:
            sys.argv = [str(modbus)]
            runpy.run_path(str(modbus), run_name="__main__")
        except SystemExit as exc:
            ok &= exc.code in (0, None)
        finally:
            sys.argv = saved
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
