"""``velab record --config BENCH`` against ``velab sim`` in another process, and the valve command.

The simulator runs as its own process (ephemeral ports, real sockets); the bench file is
written from the endpoints it prints. Killing it (SIGKILL) or freezing it (SIGSTOP) mid-run
must end the run "failed", naming the lost device, with the valve commanded safe and the file
closed and readable; ``velab valve`` reopens the valve between runs from the CLI.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import h5py
import pytest

from velab.runfiles.reader import read_run

pytestmark = pytest.mark.slow  # the integration layer: the simulated bench (tests/recording: the stages alone)

CLI = [sys.executable, "-m", "velab.cli"]


def _start_sim(tmp_path: Path):
    p = subprocess.Popen(CLI + ["sim", "--config", "default", "--ephemeral"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    eps = {}
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        line = p.stdout.readline()
        if not line or line.startswith("Ctrl-C"):
            break
        tok = line.split()
        if len(tok) >= 4 and tok[0] in ("streaming_adc", "valve", "flowmeter", "pressure_adc"):
            eps.setdefault(tok[0], []).append((tok[2], tok[3]))
    if not {"streaming_adc", "valve", "flowmeter"} <= set(eps):
        p.kill()  # (never left running behind a failed test)
        p.wait(10)
        raise AssertionError(f"velab sim did not list its endpoints: {eps}")
    pick = lambda dev, tr: next(a for t, a in eps[dev] if t == tr)  # noqa: E731
    valve = pick("valve", "tcp").split("//")[1]
    flow = pick("flowmeter", "rtu-socket")
    bench = f"""name = "velab sim process"
[recorder]
pressure_source = "streaming_adc"
valve = "valve"
flowmeter = "flowmeter"
armed_timeout_s = 120
[devices.streaming_adc]
kind = "streaming_adc"
profile = "streaming_adc"
url = "{pick('streaming_adc', 'socket')}"
[devices.valve]
kind = "valve_actuator"
profile = "valve_actuator"
transport = "tcp"
host = "{valve.rsplit(':', 1)[0]}"
port = {valve.rsplit(':', 1)[1]}
unit = 3
timeout_s = 0.5
retries = 2
[devices.flowmeter]
kind = "flowmeter"
profile = "sitrans_mag6000"
transport = "rtu"
port = "{flow}"
baudrate = 19200
unit = 2
timeout_s = 0.5
retries = 2
"""
    cfg = tmp_path / "bench.toml"
    cfg.write_text(bench)
    ports = [int(u.rsplit(":", 1)[1]) for u in (pick("streaming_adc", "socket"), valve, flow)]
    return p, cfg, ports


def _hold(ports) -> list:
    """Listen on a killed simulator's ports, never answering. Otherwise another test's simulator (three
    suites' worth of them start on ephemeral ports) can be given a freed port: the recorder's reconnect then
    reached a stranger's valve ("answers again"), found it at rest and had nothing to command. A listener
    blocks any other bind; SO_REUSEADDR only gets past the killed server's TIME_WAIT connections."""
    socks = []
    for port in ports:
        deadline = time.monotonic() + 2.0
        while True:
            s = socket.socket()
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind(("127.0.0.1", port))
                s.listen(1)
                socks.append(s)
                break
            except OSError:  # (not yet released, or already taken by another process: then not held)
                s.close()
                if time.monotonic() > deadline:
                    break
                time.sleep(0.01)
    return socks


def _record(cfg, out, *extra, wait=True):
    args = CLI + ["record", "--config", str(cfg), "--out-dir", str(out), "--pretrigger", "0.5", *extra]
    if not wait:
        return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return subprocess.run(args, capture_output=True, text=True, timeout=120)


def _recording(out: Path, timeout=60.0) -> Path:
    """Wait until the run file says the trigger was commanded (phase recording)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for f in out.glob("*.h5"):
            try:
                with h5py.File(f, "r", swmr=True) as fh:
                    kinds = [k.decode() for k in fh["entry/events/kind"][()]]
                    msgs = [m.decode() for m in fh["entry/events/message"][()]]
                if any(k == "phase" and m.startswith("recording") for k, m in zip(kinds, msgs)):
                    return f
            except (OSError, KeyError):
                pass
        time.sleep(0.05)
    raise AssertionError("the run never reached the recording phase")


@pytest.mark.timeout(180)
@pytest.mark.parametrize("how", ["SIGKILL", "SIGSTOP"])
def test_simulator_process_lost_mid_run_fails_naming_the_device(tmp_path, how):
    sim, cfg, ports = _start_sim(tmp_path)
    out = tmp_path / "runs"
    held = []
    try:
        rec = _record(cfg, out, "--duration", "60", "--no-fit", wait=False)
        path = _recording(out)
        time.sleep(0.5)
        t0 = time.monotonic()
        os.kill(sim.pid, signal.SIGKILL if how == "SIGKILL" else signal.SIGSTOP)
        if how == "SIGKILL":
            sim.wait(30)  # its sockets are closed once it is gone
            held = _hold(ports)
        stdout, stderr = rec.communicate(timeout=60)  # a hang detector; the bound is printed below
        took = time.monotonic() - t0
    finally:
        for s in held:
            s.close()
        if sim.poll() is None:
            os.kill(sim.pid, signal.SIGCONT)
            sim.kill()
        sim.wait(30)
        if rec.poll() is None:
            rec.kill()
    print(f"{how}: velab record ended {took:.1f} s after the simulator was lost")
    assert rec.returncode == 5, stderr
    assert "Traceback" not in stderr and "Traceback" not in stdout
    assert "status: failed" in stdout and "streaming_adc" in stdout
    run = read_run(path)
    assert not run.incomplete and run.status == "failed" and "streaming_adc" in run.status_reason
    safe = [m for _, k, m in run.events if "abort" in m or "safe state" in m]
    assert safe, run.events  # the valve was commanded safe (or the attempt is recorded)
    if how == "SIGKILL" and len(held) == len(ports):  # nothing else answered at the dead simulator's addresses
        assert not [m for _, k, m in run.events if k == "fault" and "answers again" in m], run.events


@pytest.mark.timeout(240)
def test_valve_command_reopens_the_valve_between_cli_runs(tmp_path):
    sim, cfg, _ = _start_sim(tmp_path)
    out = tmp_path / "runs"
    try:
        st = subprocess.run(CLI + ["valve", "status", "--config", str(cfg), "--json"], capture_output=True, text=True,
                            timeout=60)
        assert st.returncode == 0, st.stderr
        assert json.loads(st.stdout)["open"] is True
        first = _record(cfg, out, "--duration", "1", "--no-fit", "--json")
        assert first.returncode == 0, first.stderr
        assert json.loads(first.stdout)["runs"][0]["status"] == "completed"
        again = _record(cfg, out, "--duration", "1", "--no-fit")  # the valve is closed: refused, says what to do
        assert again.returncode == 3 and "velab valve open" in again.stderr
        op = subprocess.run(CLI + ["valve", "open", "--config", str(cfg)], capture_output=True, text=True, timeout=60)
        assert op.returncode == 0 and "IDLE" in op.stdout, op.stderr
        second = _record(cfg, out, "--duration", "1", "--no-fit")
        assert second.returncode == 0, second.stderr
        # close: the interlock first (a margin that makes the surge exceed the limits: refused, nothing moves)
        bad = subprocess.run(CLI + ["valve", "close", "--config", str(cfg), "--surge-margin", "5"],
                             capture_output=True, text=True, timeout=60)
        assert bad.returncode == 3 and "refused" in bad.stderr and "Traceback" not in bad.stderr
        subprocess.run(CLI + ["valve", "open", "--config", str(cfg)], capture_output=True, timeout=60, check=True)
        shut = subprocess.run(CLI + ["valve", "close", "--config", str(cfg), "--json"], capture_output=True, text=True,
                              timeout=60)
        assert shut.returncode == 0, shut.stderr
        assert json.loads(shut.stdout)["state"] == "DONE"
        # a campaign: the valve reopened and the steady state re-checked before each run
        camp = _record(cfg, out, "--duration", "1", "--no-fit", "--repeat", "2", "--reopen-valve", "--json")
        assert camp.returncode == 0, camp.stderr
        doc = json.loads(camp.stdout)
        assert doc["campaign"]["statuses"] == ["completed", "completed"]
        assert "campaign: 2 of 2 runs" in camp.stderr
    finally:
        sim.kill()
        sim.wait(30)
