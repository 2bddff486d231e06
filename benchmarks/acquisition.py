"""Acquisition benchmark: can the streaming ADC driver keep up, and at what cost over raw reading?

Runs the SADC-4 simulator in a separate process (fast mode: it streams as fast as
the reader reads, its device clock advancing by exactly 1/fs per sample) and the
reader in this process. For each case two readers take turns, each against a fresh
simulator, ``--repeat`` times (figures: the median):

* **driver**: StreamingADC through its reader thread and bounded queue, like the
  recorder (parsing, CRC, resync, sequence accounting, engineering conversion);
* **raw read** (the baseline, the transport's own ceiling): the same configuration
  commands, then a bare loop that only reads bytes from the same transport (same
  URL, same pyserial port settings, same read size) into a buffer until it has
  the same number of samples the driver delivered — no parsing, no CRC, no
  resync, no conversion.

It prints, per reader, the simulated duration, samples/s (the raw read's is the
samples/s-equivalent of the frame bytes it read), values/s, bytes/s, the lost
samples (driver: sequence gaps + queue overflow, must be 0) and the CPU time of
this process per second of data (< 1 means it would keep up in real time on one
core); then the ratios driver/raw: the throughput fraction (driver samples/s over
raw samples/s; 1.0 = the driver reads as fast as the transport delivers) and the
CPU overhead factor (driver CPU per second of data over raw CPU per second of data).
"sim CPU" is the simulator process's CPU over the wall time: near 100 % means the
simulator (one core generating frames) set the pace, not the reader.

    python benchmarks/acquisition.py                 # 10 kHz x1, 10 kHz x4 (60 s each), 50 kHz x4
    python benchmarks/acquisition.py --seconds 10 --transport pty --repeat 1

If benchmarks/acquisition_modbus.py exists (the Modbus ADC benchmark), it is run
afterwards so one script prints both.
"""

from __future__ import annotations

import argparse
import os
import re
import runpy
import statistics
import subprocess
import sys
import time
from pathlib import Path

from velab.drivers.streaming_adc import AcquisitionConfig, StreamingADC, default_profile

CASES = [  # (rate Hz, channels, headroom case?)
    (10_000, 1, False),
    (10_000, 4, False),
    (50_000, 4, True),
]
CHANNELS = ["pressure", "valve_position", "spare_2", "spare_3"]
_STOP_REPLY = re.compile(rb"OK STOP \d+\r?\n")


def _proc_cpu(pid: int) -> float:
    """CPU seconds (user + system) a live process has used so far; NaN where /proc is missing."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return float("nan")


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


def stop_simulator(proc: subprocess.Popen) -> None:
    proc.terminate()
    proc.wait(5)
    proc.stdout.close()


def run_case(rate: float, nch: int, seconds: float, transport: str) -> dict:
    """The driver: StreamingADC with its reader thread and bounded queue."""
    proc, url = start_simulator(transport)
    try:
        prof = default_profile(queue_blocks=20_000, data_timeout_s=5.0, reconnect=False)
        adc = StreamingADC(url, prof)
        adc.open()
        cfg = adc.configure(rate, CHANNELS[:nch])
        target = int(rate * seconds)
        got = 0
        sim0, cpu0, wall0 = _proc_cpu(proc.pid), time.process_time(), time.perf_counter()
        adc.start(wait_when_full=True)  # fast mode outruns real time: let back-pressure pace the device
        while got < target:
            got += adc.get_block(timeout=10).n
        stats = adc.stop()
        for b in adc.get_blocks():  # frames parsed while stopping
            got += b.n
        wall = time.perf_counter() - wall0
        cpu = time.process_time() - cpu0
        sim_cpu = _proc_cpu(proc.pid) - sim0
        adc.close()
    finally:
        stop_simulator(proc)
    data_s = stats.samples / cfg.rate_hz
    return dict(
        cfg=cfg, prof=prof, rate=cfg.rate_hz, nch=nch, block=cfg.block_samples, samples=stats.samples,
        data_s=data_s, wall=wall, sps=stats.samples / wall, values_ps=stats.samples * nch / wall,
        bytes_ps=stats.bytes_read / wall,
        lost=stats.lost + stats.queue_dropped + stats.lost_estimated, crc=stats.crc_errors,
        cpu_per_s=cpu / data_s, speedup=data_s / wall, sim_cpu=sim_cpu / wall,
    )


def run_raw(cfg: AcquisitionConfig, prof, samples: int, transport: str) -> dict:
    """The baseline: the same stream read by a bare loop (bytes into a buffer, nothing else).

    Same simulator, same configuration (rate, channels, ranges, frame size), same
    pyserial URL and settings, same read call and size as the driver's reader; reads
    until it has the frame bytes of ``samples`` samples, then STOP (and the tail up
    to its reply), like the driver's timed section.
    """
    import serial

    proc, url = start_simulator(transport)
    try:
        port = serial.serial_for_url(url, baudrate=prof.baudrate, timeout=prof.poll_s,
                                     write_timeout=prof.command_timeout_s)
        rx = bytearray()

        def command(line: str) -> None:  # set-up only, not timed
            port.write(line.encode("ascii") + b"\n")
            deadline = time.monotonic() + prof.command_timeout_s
            while b"\n" not in rx:
                if time.monotonic() > deadline:
                    raise SystemExit(f"raw read: no reply to {line!r}")
                rx.extend(port.read(1))
            reply = rx[: rx.index(b"\n")].decode("ascii", "replace").strip()
            del rx[: rx.index(b"\n") + 1]
            if not reply.startswith("OK"):
                raise SystemExit(f"raw read: {line!r} -> {reply!r}")

        command(f"RATE {cfg.rate_hz:.10g}")
        command("CHAN " + ",".join(str(c.index) for c in cfg.channels))
        for c in cfg.channels:
            command(f"RANGE {c.index} {c.range}")
        command(f"BLOCK {cfg.block_samples}")
        flen, k = cfg.frame_len, cfg.block_samples
        start_reply = len(b"OK START\n")
        want = start_reply + -(-samples // k) * flen
        chunk = int(max(flen, min(1 << 16, cfg.rate_hz / k * flen * prof.poll_s / 2)))  # the driver's read size
        buf = bytearray()
        got = 0
        sim0, cpu0, wall0 = _proc_cpu(proc.pid), time.process_time(), time.perf_counter()
        port.write(b"START\n")
        while got < want:
            data = port.read(max(port.in_waiting, chunk))
            got += len(data)
            buf += data
            if len(buf) >= 1 << 22:  # a recorder would hand this on; keep the footprint bounded
                buf.clear()
        port.write(b"STOP\n")
        tail = bytearray()
        deadline = time.monotonic() + prof.command_timeout_s
        while (m := _STOP_REPLY.search(tail)) is None:
            if time.monotonic() > deadline:
                raise SystemExit("raw read: no reply to STOP")
            data = port.read(max(port.in_waiting, flen))
            got += len(data)
            buf += data
            tail = tail[-32:] + data
        wall = time.perf_counter() - wall0
        cpu = time.process_time() - cpu0
        sim_cpu = _proc_cpu(proc.pid) - sim0
        port.close()
    finally:
        stop_simulator(proc)
    frame_bytes = got - start_reply - len(m.group(0))
    samples_eq = frame_bytes / flen * k
    data_s = samples_eq / cfg.rate_hz
    return dict(
        samples=samples_eq, data_s=data_s, wall=wall, sps=samples_eq / wall,
        values_ps=samples_eq * len(cfg.channels) / wall, bytes_ps=got / wall,
        cpu_per_s=cpu / data_s, speedup=data_s / wall, sim_cpu=sim_cpu / wall,
    )


def _median(runs: list[dict], key: str) -> float:
    return statistics.median(r[key] for r in runs)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="simulated seconds per case (default 60)")
    ap.add_argument("--transport", choices=["tcp", "pty"], default="tcp")
    ap.add_argument("--repeat", type=int, default=5, help="driver / raw-read runs per case, alternating (median; default 5)")
    ap.add_argument("--no-modbus", action="store_true", help="skip benchmarks/acquisition_modbus.py")
    args = ap.parse_args(argv)
    repeat = max(1, args.repeat)

    print(f"Streaming ADC (SADC-4) over {'socket://127.0.0.1' if args.transport == 'tcp' else 'pty'}, "
          f"simulator in a subprocess (fast mode), {os.cpu_count()} cores, median of {repeat} run(s) per reader")
    print("baseline 'raw read': the same stream read by a bare loop from the same transport "
          "(no parsing, CRC, resync or conversion)")
    hdr = (f"{'case':<25}{'reader':<10}{'data s':>7}{'wall s':>7}{'x real':>7}{'samples/s':>12}{'values/s':>12}"
           f"{'MB/s':>7}{'lost':>6}{'CPU s/s data':>13}{'sim CPU':>8}{'thru/raw':>9}{'CPU x raw':>10}")
    print(hdr)
    ok = True
    for rate, nch, headroom in CASES:
        drv, raw = [], []
        for _ in range(repeat):
            d = run_case(rate, nch, args.seconds, args.transport)
            drv.append(d)
            raw.append(run_raw(d["cfg"], d["prof"], d["samples"], args.transport))
        name = f"{rate / 1000:g} kHz x {nch} ch" + (" (headroom)" if headroom else "")
        lost = sum(r["lost"] for r in drv)
        m = {key: (_median(drv, key), _median(raw, key))
             for key in ("data_s", "wall", "speedup", "sps", "values_ps", "bytes_ps", "cpu_per_s", "sim_cpu")}
        thru = m["sps"][0] / m["sps"][1]
        cpu_x = m["cpu_per_s"][0] / m["cpu_per_s"][1]
        for i, (who, lost_txt, ratios) in enumerate((
                ("driver", f"{lost:d}", f"{thru:9.2f}{cpu_x:9.1f}x"),
                ("raw read", "-", f"{'(baseline)':>19}"))):
            print(f"{name if i == 0 else '':<25}{who:<10}{m['data_s'][i]:7.1f}{m['wall'][i]:7.2f}{m['speedup'][i]:7.1f}"
                  f"{m['sps'][i]:12,.0f}{m['values_ps'][i]:12,.0f}{m['bytes_ps'][i] / 1e6:7.1f}{lost_txt:>6}"
                  f"{m['cpu_per_s'][i]:13.4f}{m['sim_cpu'][i]:8.0%}{ratios}")
        ok &= lost == 0 and all(r["data_s"] >= args.seconds for r in drv)
    print("thru/raw: driver samples/s / raw-read samples/s (1.00 = as fast as the transport delivers); "
          "CPU x raw: driver CPU per s of data / raw-read CPU per s of data")
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
