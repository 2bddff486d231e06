"""Faults from a sim config's ``[[faults.schedule]]``, end to end through the CLI as a user runs it:
``velab record --simulate --sim-config FILE`` in its own process (the config is read, checked, the
simulated rig started in-process, the faults fire at their instants of the run). A few
representative cases here; the rest go through the API (tests/recording/test_record_quality.py: sensor
faults at arm and mid-record; tests/recording/test_record_trigger.py: the trigger instant).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from record_helpers import cli
from velab.runfiles.reader import read_run

pytestmark = pytest.mark.slow  # the integration layer: the simulated bench (tests/recording: the stages alone)

CLI = [sys.executable, "-m", "velab.cli"]
DEFAULT = Path(__file__).resolve().parents[2] / "configs" / "sim" / "default.toml"

CASES = {
    # a lost TRIGGER reply: the actuator carried it out; read back -> the run goes on, marked
    "trigger_reply_lost": ('device = "valve"\nfault = { drop_reply = true, count = 1 }\nat = "trigger"\n',
                           6, "completed-with-faults", "TRIGGER reply lost"),
    # the actuator dies at the trigger (for good): unknown outcome -> failed, valve named, exit 5
    "valve_dies_at_trigger": ('device = "valve"\nfault = { disconnect = true }\nat = "trigger"\n',
                              5, "failed", "trigger outcome unknown"),
    # a 22 mA transducer 0.3 s after the trigger, clearing 0.3 s later: a sensor fault, never a ceiling abort
    "sensor_fault_clears": ('device = "rig"\nfault = { channel_mA = { 0 = 22.0 } }\nat = "trigger+0.3"\n'
                            'duration_s = 0.3\n', 6, "completed-with-faults", "sensor_fault"),
    # the streaming ADC falls silent for good 0.2 s after ARM: no pressure -> failed, naming it
    "adc_silent_at_arm": ('device = "streaming_adc"\nfault = { silent = true }\nat = "arm+0.2"\n',
                          5, "failed", "streaming_adc"),
}


@pytest.mark.timeout(180)
@pytest.mark.parametrize("case", CASES)
def test_scheduled_fault_from_a_sim_config_through_the_cli(tmp_path, case):
    entry, code, status, said = CASES[case]
    # 4 s of record (1/3 s of host time at the fast clock): the record ends its duration after the stroke's
    # latest start as the blocks bound it, which lags the true start by up to 0.17 s of host time at load 25;
    # 1.5 s (0.125 s) let a loaded host end the record before the feedback showed the stroke ("no stroke seen")
    cfg = tmp_path / "faulty.toml"
    cfg.write_text(DEFAULT.read_text() + "\n[[faults.schedule]]\n" + entry)
    p = subprocess.run(CLI + ["record", "--simulate", "--sim-config", str(cfg), "--fast", "--no-fit", "--json",
                              "--duration", "4.0", "--pretrigger", "1.0", "--out-dir", str(tmp_path / "runs")],
                       capture_output=True, text=True, timeout=150)
    assert "Traceback" not in p.stderr and "Traceback" not in p.stdout, p.stderr
    assert p.returncode == code, (p.returncode, p.stderr[-2000:])
    run_doc = json.loads(p.stdout)["runs"][0]
    assert run_doc["status"] == status and run_doc["exit_code"] == code
    text = run_doc["reason"] + " " + " ".join(run_doc["faults"])
    assert said in text, text
    assert "pressure ceiling" not in text
    run = read_run(run_doc["path"])  # closed, readable, the same verdict, the fault in its event log
    assert not run.incomplete and run.status == status
    assert any(k == "fault" for _, k, _ in run.events)


def test_a_bad_schedule_entry_is_one_line_naming_file_and_key(tmp_path):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(DEFAULT.read_text() + '\n[[faults.schedule]]\ndevice = "valve"\nfault = { drop_reply = 1 }\n'
                                         'at = "trigger"\n')
    # (refused as the config is read: through main() in this process; the cases above are the real processes)
    p = cli(["record", "--simulate", "--sim-config", str(cfg), "--fast", "--no-fit",
             "--out-dir", str(tmp_path / "runs")])
    assert p.returncode == 2 and "Traceback" not in p.stderr
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "bad.toml" in lines[0] and "drop_reply = 1: must be true or false" in lines[0], lines
    assert not list((tmp_path / "runs").glob("*.h5"))  # nothing was recorded
