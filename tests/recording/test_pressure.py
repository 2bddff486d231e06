"""velab.recording.pressure: the acquisition thread on a scripted pressure source and a recording
hooks object (no sockets, no simulated rig): blocks with their quality codes, transient faults
said once, a fatal error or a stall ending the run, a bounded stop."""

from __future__ import annotations

import numpy as np
import pytest

from stage_helpers import RecordingHooks, block
from velab.drivers.base import DeviceDisconnected
from velab.drivers.pressure_source import BlockRead
from velab.recording.pressure import PressureStage
from velab.recording.types import DeviceFailure


class ScriptedSource:
    """A PressureSource whose reads are scripted (then empty); ``done`` is set when the script ends."""

    name = "adc"

    def __init__(self, reads, channels=("pressure", "valve_position"), hint=""):
        self.reads, self._channels, self.hint, self.stopped = list(reads), channels, hint, False

    def channels(self):
        return self._channels

    def configure(self, rate_hz, pressure=None):
        self.rate, self.pressure = rate_hz, pressure
        return rate_hz

    def start(self):
        return self.rate

    def read_blocks(self, wait_s=0.2):
        if not self.reads:
            return BlockRead()
        r = self.reads.pop(0)
        if isinstance(r, BaseException):
            raise r
        return r

    def stall_hint(self):
        return self.hint

    def stop(self):
        self.stopped = True

    def spot_heads(self, rate_hz, channels):
        raise DeviceDisconnected("adc: gone")


def run(reads, stall_s=0.05, **kw):
    rec, got = RecordingHooks(), []
    stage = PressureStage(ScriptedSource(reads, **kw))
    stage.configure(1000.0)
    stage.start(stall_s, lambda b, codes: got.append((b, codes)), rec.hooks)
    assert rec.ended.wait(5.0)
    assert stage.stop() == ""
    return stage, rec, got


def test_blocks_arrive_with_their_quality_codes_then_a_stall_ends_the_run():
    codes = np.zeros((4, 2), np.uint8)
    codes[2, 0] = 3
    b = block(0, 4, codes=codes)
    stage, rec, got = run([BlockRead((b,))], hint=" (device silent)")
    assert got[0][0] is b and got[0][1]["pressure"].tolist() == [0, 0, 3, 0]
    assert got[0][1]["valve_position"].tolist() == [0, 0, 0, 0]
    (status, reason), = rec.ends
    assert status == "failed" and "no pressure samples for 0.05 s (device silent)" in reason
    assert stage.outcome.startswith("failed: no pressure samples")


def test_a_transient_error_is_one_fault_then_answers_again():
    reads = [BlockRead(error="timeout", note="retrying")] * 3 + [BlockRead((block(0, 2),))]
    _, rec, got = run(reads)
    assert [f[1] for f in rec.faults[:2]] == ["timeout (retrying)", "answers again after: timeout"]
    assert len(got) == 1


def test_a_stall_after_transient_errors_names_the_last_one():
    _, rec, _ = run([BlockRead(error="timeout", note="retrying")] * 50, stall_s=0.0)
    assert "(last error: timeout)" in rec.ends[0][1]


def test_a_fatal_error_ends_the_run_naming_the_source():
    _, rec, _ = run([DeviceDisconnected("adc: connection lost")])
    assert rec.ends == [("failed", "adc (pressure source): acquisition failed: connection lost")]
    assert rec.faults[0][1] == "acquisition failed: connection lost"


def test_a_source_without_a_pressure_channel_is_refused():
    with pytest.raises(DeviceFailure, match="no pressure channel"):
        PressureStage(ScriptedSource([], channels=(None, "valve_position")))


def test_a_dead_device_at_the_look_is_a_device_failure():
    with pytest.raises(DeviceFailure, match="pressure check failed"):
        PressureStage(ScriptedSource([])).look(1000.0)
