"""The streaming ADC with faults at instants of the simulation clock: silence, corruption,
disconnect (and back, or for good). Each surfaces as a named condition, gaps counted exactly."""

from __future__ import annotations

import time

import numpy as np
import pytest

from sim_helpers import stream_profile

from velab.drivers.base import DeviceDisconnected, DeviceTimeout, StreamSilent
from velab.drivers.bench import open_device
from velab.drivers.streaming_adc import StreamingADC
from velab.simulators.bench import SimulatedBench
from velab.simulators.clock import ManualClock, RealTimeClock
from velab.simulators.schedule import FaultSchedule, Instant, RunInstants, ScheduledFault
from velab.simulators.streaming_adc import StreamingADCSimulator, ramp_source

pytestmark = pytest.mark.timeout(120)

FS = 10_000
K = 20  # samples per frame


profile = stream_profile


class Rig:
    """A manual clock, a schedule, a simulator on it and a started driver."""

    def __init__(self, transport="tcp", **prof):
        self.clock = ManualClock()
        self.schedule = FaultSchedule(RunInstants(0.0))
        self.sim = StreamingADCSimulator(ramp_source, realtime=True, clock=self.clock, schedule=self.schedule,
                                         name="adc")
        url = self.sim.serve_tcp() if transport == "tcp" else self.sim.serve_pty()
        self.adc = StreamingADC(url, profile(**prof))
        self.adc.configure(FS, ["pressure"], block_samples=K)
        self.adc.start()

    def fault(self, t0, duration_s=None, **fault):
        """A fault from device time t0 (s after START) on."""
        t_start = self.sim._t_source0
        return self.schedule.add(ScheduledFault("adc", fault, Instant("abs", t_start + t0), duration_s))

    def run_until(self, device_time_s, blocks, step=0.01):
        """Advance the clock in small steps (frames follow it), collecting blocks."""
        deadline = time.monotonic() + 60
        while self.clock.now() - self.sim._t_source0 < device_time_s:
            assert time.monotonic() < deadline
            self.clock.advance(step)
            time.sleep(0.003)
            blocks += self.adc.get_blocks()

    def drain(self, device_time_s, blocks):
        """Collect blocks until the driver has every frame the clock has made by device_time_s (a state,
        not a sleep: on a loaded host the simulator's thread and the driver's reader lag the clock)."""
        last = int(round(device_time_s * FS)) - K  # the first sample of the last whole frame
        deadline = time.monotonic() + 30
        while not any(b.first_index + b.n > last for b in blocks):
            assert time.monotonic() < deadline, "the frames made by the clock never arrived"
            time.sleep(0.005)
            blocks += self.adc.get_blocks()

    def close(self):
        self.adc.close()
        self.sim.close()


@pytest.fixture(params=["tcp", "pty"])
def rig(request):
    r = Rig(request.param)
    yield r
    r.close()


def indices(blocks):
    return np.concatenate([b.first_index + np.arange(b.n) for b in blocks])


def test_silence_window_is_an_exact_overrun_gap(rig):
    rig.fault(0.2, 0.1, silent=True)
    blocks = []
    rig.run_until(0.5, blocks)
    rig.drain(0.5, blocks)
    idx = indices(blocks)
    silent = (idx >= 2000) & (idx < 3000)
    assert not silent.any() and idx.max() >= 4000  # nothing from inside the window, data after it
    after = next(b for b in blocks if b.first_index >= 3000)
    assert after.first_index == 3000 and after.lost_before == 1000 and after.overrun  # the FIFO overflowed
    assert rig.adc.stats.lost == 1000 and rig.sim.stats.frames_silenced == 50
    assert sum(b.lost_before for b in blocks) == 1000


def test_corrupted_frames_window_counted(rig):
    rig.fault(0.1, 0.05, corrupt=True)
    blocks = []
    rig.run_until(0.3, blocks)
    rig.drain(0.3, blocks)
    after = next(b for b in blocks if b.first_index >= 1500)
    assert after.first_index == 1500 and after.lost_before == 500 and not after.overrun
    assert 0 < after.rejected_frames <= 25 or rig.adc.stats.resyncs > 0
    assert rig.adc.stats.lost == 500 and rig.sim.stats.frames_corrupted == 25


def test_silent_for_good_is_stream_silent_within_data_timeout():
    r = Rig(data_timeout_s=0.5)
    try:
        r.fault(0.1, None, silent=True)
        blocks = []
        r.run_until(0.1, blocks)
        t0 = time.monotonic()
        with pytest.raises(StreamSilent, match="no valid frame for 0.5 s") as ei:
            while True:
                r.clock.advance(0.01)
                blocks.append(r.adc.get_block(timeout=5))
        assert time.monotonic() - t0 < 10  # a deadline, not a benchmark: the silence is named in bounded time
        assert ei.value.reason == "silent" and r.adc.condition == "failed"
        assert isinstance(ei.value, DeviceTimeout)
    finally:
        r.close()


@pytest.mark.parametrize("transport", ["tcp", "pty"])
def test_disconnect_window_then_reconnected(transport):
    r = Rig(transport)
    try:
        r.fault(0.1, 0.2, disconnect=True)
        blocks = []
        r.run_until(0.12, blocks)
        seen = set()
        deadline = time.monotonic() + 30
        while not any(b.restarted for b in blocks):
            assert time.monotonic() < deadline
            seen.add(r.adc.condition)
            r.clock.advance(0.005)
            time.sleep(0.005)
            blocks += r.adc.get_blocks()
        assert "reconnecting" in seen
        new = next(b for b in blocks if b.restarted)
        assert new.segment == 1 and new.first_index == 0 and new.lost_before > 0
        assert r.clock.now() - r.sim._t_source0 >= 0 and r.adc.stats.reconnects == 1
        assert r.sim.stats.disconnects == 1
    finally:
        r.close()


def test_disconnect_for_good_is_named_within_reconnect_timeout():
    r = Rig(reconnect_timeout_s=1.0)
    try:
        r.fault(0.05, None, disconnect=True)
        blocks = []
        r.run_until(0.06, blocks)
        t0 = time.monotonic()
        with pytest.raises(DeviceDisconnected, match="could not reconnect within 1 s") as ei:
            while True:
                r.clock.advance(0.01)
                r.adc.get_block(timeout=5)
        assert time.monotonic() - t0 < 15
        assert ei.value.reason == "disconnected" and ei.value.device == "streaming ADC"
        assert r.adc.condition == "failed"
    finally:
        r.close()


def test_real_time_bench_fault_at_trigger_offset():
    """Real time (RealTimeClock): a silence from trigger+0.3 s for 0.2 s, triggered through the valve."""
    cfg = {"rig": "perugia", "material": "A", "devices": {
        "adc": {"kind": "streaming_adc", "endpoints": [{"transport": "socket"}]},
        "valve": {"kind": "valve_actuator", "endpoints": [{"transport": "tcp"}]}},
        "faults": {"schedule": [{"device": "adc", "fault": {"silent": True}, "at": "trigger+0.3",
                                 "duration_s": 0.2}]}}
    with SimulatedBench(cfg, clock=RealTimeClock(), ephemeral=True) as sim:
        bench = sim.bench(valve={"timeout_s": 1.0})
        v = open_device(bench.devices["valve"])
        adc = StreamingADC(sim.endpoint("adc").address, profile())
        try:
            adc.configure(1000, ["pressure"], block_samples=10)
            adc.start()
            t_start = sim.handles["adc"].simulators[0]._t_source0
            v.arm()
            v.trigger()
            t_trig = sim.rig.trigger_time
            blocks = []
            while sim.clock.now() < t_trig + 1.0:
                blocks.append(adc.get_block(timeout=5))
            stats = adc.stop()
        finally:
            adc.close()
            v.close()
    # device times on the clock's axis: the gap is the window, to the frame (10 ms: a frame whose
    # first sample is before the instant is sent whole)
    t = t_start + indices(blocks) / 1000.0
    t0, t1 = t_trig + 0.3, t_trig + 0.5
    assert not ((t >= t0 + 0.01) & (t < t1 - 0.01)).any()
    assert ((t >= t0 - 0.02) & (t < t0)).any()  # data right up to the instant
    gap = next(b for b in blocks if b.lost_before)
    first_after = t_start + gap.first_index / 1000.0
    assert first_after >= t1 - 0.01 and first_after < t1 + 0.02  # frames of 10 ms: the window's frame grid
    assert gap.overrun and stats.lost == gap.lost_before


def test_cleared_instants_anchor_nothing_of_the_last_session():
    inst = RunInstants(0.0)
    inst.mark("trigger", 5.0)
    f = ScheduledFault("pressure_adc", {"silent": True}, Instant.parse("trigger+0.5"), 1.0, created_s=2.0)
    assert f.windows(inst) and f.active_at(5.6, inst)
    inst.clear(start=3.0)
    assert inst.times("trigger") == [] and inst.times("start") == [3.0]
    assert not f.windows(inst) and not f.active_at(5.6, inst)
    inst.mark("trigger", 7.0)
    assert f.active_at(7.6, inst)
