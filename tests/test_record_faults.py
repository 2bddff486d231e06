"""Faults and bad conditions during a recording: SIGKILL, SIGTERM/Ctrl-C, device faults.

Subprocess tests run ``velab record --simulate --fast`` (the simulated rig in the child,
over real sockets); in-process tests inject faults into the running SimulatedBench.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from velab.recorder import Recorder, RecordSettings
from velab.runfile import read_run


def _spawn(out: Path, *extra):
    return subprocess.Popen(
        [sys.executable, "-m", "velab.cli", "record", "--simulate", "--fast", "--out-dir", str(out), *extra],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _samples_in(out: Path, timeout=60.0, need=0) -> tuple[Path, int]:
    """Follow the file as a SWMR reader until it holds `need` samples."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        files = list(out.glob("*.h5"))
        if files:
            try:
                with h5py.File(files[0], "r", swmr=True) as fh:
                    n = fh["entry/data/time"].shape[0]
                if n >= need:
                    return files[0], n
            except (OSError, KeyError):
                pass
        time.sleep(0.02)
    raise AssertionError(f"no run file with {need} samples in {out}")


def test_sigkill_keeps_every_flushed_sample(tmp_path):
    p = _spawn(tmp_path, "--duration", "22", "--no-fit")
    try:
        path, seen = _samples_in(tmp_path, need=9000)  # 2 s baseline + 7 s of transient
        p.kill()
        p.wait(30)
    finally:
        if p.poll() is None:
            p.kill()
    run = read_run(path)
    assert run.incomplete and run.status == "recording"
    assert run.n_samples >= seen  # everything a reader saw before the kill is in the file
    assert np.allclose(np.diff(run.time_s), 1e-3)
    assert np.array_equal(run.channels["sample_index"], np.arange(run.n_samples))
    info = subprocess.run([sys.executable, "-m", "velab.cli", "info", str(path)], capture_output=True, text=True,
                          timeout=60)
    assert "INCOMPLETE" in info.stdout
    fit = subprocess.run([sys.executable, "-m", "velab.cli", "fit", str(path), "--window", "4", "--models", "1-3",
                          "--json", "--no-save"], capture_output=True, text=True, timeout=120)
    assert fit.returncode == 0, fit.stderr


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_sigterm_and_ctrl_c_stop_cleanly(tmp_path, sig):
    p = _spawn(tmp_path, "--duration", "22", "--no-fit")
    try:
        path, seen = _samples_in(tmp_path, need=3000)
        p.send_signal(sig)
        out, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 130, err
    assert "Traceback" not in err
    run = read_run(path)
    assert run.status == "stopped" and not run.incomplete
    assert run.n_samples >= seen
    assert any(k == "status" for _, k, _ in run.events)


def _record(tmp_path, before=None, during=None, **kw):
    s = RecordSettings(duration_s=kw.pop("duration_s", 6.0), fit=False, out_dir=tmp_path, **kw)
    with Recorder.simulated(s, clock="fast") as rec:
        if before:
            before(rec.sim)
        if during:
            rec.add_listener(lambda ev: during(rec.sim, ev))
        summary = rec.run()
    return summary


def test_flowmeter_timeout_does_not_stop_the_pressure_recording(tmp_path):
    fired = []

    def during(sim, ev):
        if ev.kind == "phase" and ev.data["phase"] == "transient" and not fired:
            fired.append(1)
            sim.faults["flowmeter"].set(silent=True)

    summary = _record(tmp_path, during=during)
    assert summary.status == "completed" and summary.lost_samples == 0
    run = read_run(summary.path)
    assert run.status == "completed" and "flowmeter" in run.status_reason
    assert run.duration_after_trigger_s > 5.9
    assert any(k == "fault" and "flowmeter" in m for _, k, m in run.events)


def test_streaming_adc_disconnect_is_a_recorded_gap(tmp_path):
    def before(sim):  # the link drops ~3 s into the recording, comes back 0.2 s later
        sim.faults["streaming_adc"].set(disconnect_after_frames=50, reconnect_delay_s=0.2)

    summary = _record(tmp_path, before=before)
    assert summary.status == "completed"
    assert summary.gaps >= 1 and summary.lost_samples > 0
    run = read_run(summary.path)
    assert run.gaps and "reconnected" in run.status_reason
    idx = run.channels["sample_index"]
    assert np.all(np.diff(idx) >= 1) and (np.diff(idx) > 1).sum() == len(run.gaps)  # never interpolated
    assert run.duration_after_trigger_s > 5.0


def test_valve_fault_during_the_manoeuvre_aborts(tmp_path):
    def before(sim):
        sim.rig.faults.valve_fault_after_s = 0.08

    summary = _record(tmp_path, before=before)
    assert summary.status == "aborted" and summary.exit_code == 4
    assert "FAULT" in summary.reason
    assert read_run(summary.path).status == "aborted"
