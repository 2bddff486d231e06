"""velab.recording.writer alone: typed operations onto a fake RunWriter, in order, through one table;
a failed write ends the run as a storage failure and the file is still closed."""

from __future__ import annotations

import numpy as np

from stage_helpers import RecordingHooks
from velab.recording.ops import Append, Event, Gap, Slow, Trigger, Value
from velab.recording.writer import WriterStage


class FakeRunWriter:
    def __init__(self, path, fail_on=None):
        self.path, self.calls, self.fail_on = path, [], fail_on

    def _call(self, name, *args, **kw):
        if name == self.fail_on:
            raise OSError("No space left on device")
        self.calls.append((name, args, kw))

    def append(self, t, **channels):
        self._call("append", t.size, **{k: v.size for k, v in channels.items()})

    def event(self, t, kind, text=""):
        self._call("event", t, kind, text)

    def gap(self, sample, lost):
        self._call("gap", sample, lost)

    def set_trigger_time(self, t):
        self._call("trigger", t)

    def set_value(self, path, value):
        self._call("value", path, value)

    def append_slow(self, name, t, value, epoch_s=None):
        self._call("slow", name, t, value, epoch_s=epoch_s)

    def flush(self):
        self._call("flush")

    def close(self, status, reason=""):
        self.calls.append(("close", (status, reason), {}))


def test_every_operation_reaches_the_file_in_order_then_it_is_closed(tmp_path):
    w, rec = FakeRunWriter(tmp_path / "run.h5"), RecordingHooks()
    stage = WriterStage(w, 1000.0, 0.05, rec.hooks)
    t = np.arange(10) / 1000.0
    for op in (Append(t, {"head": t}), Event(0.1, "operator", "armed"), Gap(10, 5), Trigger(0.5),
               Value("manoeuvre/trigger_host_time", 123.0), Slow("flow", 0.2, 0.01, 99.0)):
        stage.put(op)
    assert stage.close("completed", "")
    names = [c[0] for c in w.calls if c[0] != "flush"]
    assert names == ["append", "event", "gap", "trigger", "value", "slow", "close"]
    assert w.calls[-1] == ("close", ("completed", ""), {}) and not stage.error and not rec.ends


def test_a_failed_write_ends_the_run_and_the_file_is_still_closed(tmp_path):
    w, rec = FakeRunWriter(tmp_path / "run.h5", fail_on="gap"), RecordingHooks()
    stage = WriterStage(w, 1000.0, 0.05, rec.hooks)
    stage.put(Gap(0, 1))
    assert rec.ended.wait(5.0)
    assert rec.ends[0][0] == "failed" and "storage failure" in rec.ends[0][1]
    assert rec.faults[0][2] == "storage"
    assert stage.close("failed", "")
    assert w.calls[-1][0] == "close" and "storage failure" in w.calls[-1][1][1]
