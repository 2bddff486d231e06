"""velab.recording.timeline alone: synthetic blocks in, writer operations and hooks out (no devices,
no clock): the axis, the baseline, gaps, quality, the ceiling, the trigger, the fit window, the
steady head (the fit path's rule, velab.fitting.window)."""

from __future__ import annotations

import numpy as np
import pytest

from stage_helpers import RecordingHooks, block, codes_of
from velab.drivers.base import head_to_pressure_pa
from velab.fitting.window import steady_head
from velab.recording.ops import Append, Gap, Trigger
from velab.recording.settings import RecordSettings
from velab.recording.timeline import Timeline
from velab.recording.transducers import TransducerChannel
from velab.simulators.clock import ManualClock

FS = 1000.0


def make(pretrigger_s=1.0, duration_s=3.0, fit_window_s=2.0, ceiling=100.0, host=None, **kw):
    s = RecordSettings(pretrigger_s=pretrigger_s, duration_s=duration_s, fit_window_s=fit_window_s, fit=True,
                       intermediate_fits=False, sample_rate_hz=FS)
    rec, ops, closed, baseline = RecordingHooks(), [], [], []
    tl = Timeline(s, FS, (10.0, 0.0, 0.0), ceiling, "pressure", "valve_position", rec.hooks, ops.append,
                  lambda w, final: closed.append((w, final)), on_baseline=lambda: baseline.append(True),
                  now=(host or ManualClock()).now, **kw)
    return tl, rec, ops, closed, baseline


def feed(tl, first, n, host=None, arrival=None, **kw):
    """A block of samples [first, first + n); with ``host`` (the host's clock as the time line reads it, a
    ManualClock): it arrives at host time ``arrival`` (default: when its last sample was made, device and
    host clocks both starting at 0)."""
    if host is not None:
        host.set((first + n) / FS if arrival is None else arrival)
    b = block(first, n, rate_hz=FS, **kw)
    tl.process(b, codes_of(b))


def test_the_axis_starts_at_minus_the_pretrigger_and_the_baseline_completes_once():
    tl, rec, ops, _, baseline = make()
    for i in range(12):
        feed(tl, 100 * i, 100)
    c = tl.counters()
    assert c.n_written == 1200 and c.now_axis == pytest.approx(0.2) and c.baseline_complete
    assert baseline == [True]
    appends = [op for op in ops if isinstance(op, Append)]
    assert appends[0].t[0] == pytest.approx(-1.0) and set(appends[0].channels) >= {"head", "pressure_quality"}
    assert [k for k, _ in rec.emitted] == ["samples"] * 12 and not rec.faults and not rec.ends


def test_lost_samples_are_a_gap_op_and_a_fault():
    tl, rec, ops, _, _ = make()
    feed(tl, 0, 100)
    feed(tl, 150, 100, lost_before=50)
    assert [op for op in ops if isinstance(op, Gap)] == [Gap(100, 50)]
    assert tl.counters().lost == 50 and tl.counters().gaps == 1
    assert rec.faults[0][2] == "samples_lost" and "50 samples lost before sample 150" in rec.faults[0][1]


def test_a_flagged_pressure_before_the_trigger_aborts_the_run():
    tl, rec, _, _, _ = make()
    codes = np.zeros((100, 2), np.uint8)
    codes[40:, 0] = 3  # open loop
    feed(tl, 0, 100, codes=codes)
    assert rec.faults[0][2] == "quality" and tl.counters().flagged == 60
    assert rec.ends[0][0] == "aborted" and "before the trigger" in rec.ends[0][1]


def test_a_head_above_the_ceiling_aborts_the_run():
    tl, rec, _, _, _ = make(ceiling=50.0)
    feed(tl, 0, 100, head_m=np.r_[np.full(50, 30.0), np.full(50, 60.0)])
    assert rec.ends[0][0] == "aborted" and rec.ends[0][1].startswith("pressure ceiling")


def test_the_trigger_window_and_end_from_the_sample_clock():
    host = ManualClock()
    tl, rec, ops, closed, _ = make(host=host)
    for i in range(15):
        feed(tl, 100 * i, 100, host)
    t_est = tl.mark_trigger()  # the last block arrived at host 1.5 s, the command now: sample 1500
    assert t_est == pytest.approx(0.5) and tl.commit_trigger()
    assert [op for op in ops if isinstance(op, Trigger)] == [Trigger(t_est)]
    for i in range(15, 45):  # the valve never moves here: the trigger stays the command's estimate
        feed(tl, 100 * i, 100)
    assert closed == [(2.0, True)] and tl.counters().window_closed
    assert rec.ends == [("completed", "")]  # trigger + duration reached
    assert any("no stroke seen" in f[1] for f in rec.faults)
    r = tl.fit_window(2.0)
    assert r.trigger_time_s == t_est and r.window_s == 2.0 and not r.note and r.section_heads == {}
    assert r.t[-1] == pytest.approx(t_est + 2.0 - 1 / FS) and r.position.size == r.t.size == r.head.size


def test_the_trigger_is_estimated_from_the_block_that_waited_least_not_the_last_one():
    """A loaded host at the fast clock: the stream's blocks arrive on time for 1 s, then queue up (the
    acquisition thread starved) and the last ones processed are 1.4 s of samples behind the device when
    the trigger is commanded. The estimate is where the device is (the block that waited least, plus
    the samples made since), not the last block's index plus the time since it came (which put a
    real run's trigger 6.5 s early: its record ended before the stroke was in)."""
    scale = 12.0  # device seconds per host second
    host = ManualClock()
    tl, rec, ops, _, _ = make(host=host, clock_scale=scale)
    for i in range(10):  # on time: block i's last sample made at host (100 i + 100) / FS / scale
        feed(tl, 100 * i, 100, host, arrival=(100 * i + 100) / FS / scale)
    for i in range(10, 15):  # late: the backlog arrives at host 3.0 s / scale, the device at sample 3000
        feed(tl, 100 * i, 100, host, arrival=2.9 / scale)
    host.set(3.0 / scale)
    t_est = tl.mark_trigger()
    assert t_est == pytest.approx(3.0 - 1.0, abs=1.5 / FS)  # the device's sample 3000 (the old rule: 0.6)
    assert tl.counters().now_axis == pytest.approx(0.5)  # the samples themselves are still behind
    (kind, text), = [entry for entry in rec.logged if entry[0] == "trigger"]
    assert "lags the device by about 1.50 s" in text
    assert tl.commit_trigger() and [op for op in ops if isinstance(op, Trigger)] == [Trigger(t_est)]
    # the record runs to the estimate + its duration on the samples' own axis, however late they come
    for i in range(15, 60):
        feed(tl, 100 * i, 100, host, arrival=4.0 / scale)
    assert rec.ends == [("completed", "")]
    assert tl.counters().n_written == pytest.approx(1000 + (t_est + 3.0) * FS, abs=1)


@pytest.mark.parametrize("after_s, fault", [(0.1, False), (1.0, True)])
def test_a_run_ended_before_its_stroke_could_be_seen_is_not_a_feedback_fault(after_s, fault):
    """Stopped 0.1 s after the trigger's estimate (the commanded opening passes 10 % 0.22 s after the stroke's
    start on beta 10, gamma 0): the estimate is kept and the log says why, no fault. Stopped 1 s after it with the feedback
    still at 100 %: no stroke seen, a valve fault."""
    host = ManualClock()
    tl, rec, ops, _, _ = make(host=host)
    for i in range(15):
        feed(tl, 100 * i, 100, host)
    t_est = tl.mark_trigger()
    assert tl.commit_trigger()
    n = int(after_s * FS)
    feed(tl, 1500, n, host)  # the valve still open in the feedback
    tl.finish()
    feedback = [f for f in rec.faults if "no stroke seen" in f[1]]
    assert bool(feedback) == fault
    noted = [text for kind, text in rec.logged if "ended before the valve's stroke" in text]
    assert bool(noted) != fault
    assert [op.t for op in ops if isinstance(op, Trigger)] == [t_est]


def test_a_stroke_whose_samples_were_lost_is_not_called_stuck_feedback():
    """The samples over the stroke were lost (the opening passes 90 % and 10 % 0.22 s either side of its
    midpoint, 0.3 s after the estimate here; the gap runs from 0.05 s to 0.6 s after the estimate): the feedback
    did close, so it is not "stuck or disconnected"; the fault says the stroke passed its band with no sample
    inside it, and the trigger stays the command's estimate."""
    host = ManualClock()
    tl, rec, ops, _, _ = make(host=host)  # beta 10, gamma 0
    for i in range(15):
        feed(tl, 100 * i, 100, host)
    t_est = tl.mark_trigger()
    assert tl.commit_trigger()

    def opening(first, n):
        t = (first + np.arange(n) - 1000) / FS
        return 100.0 / (1.0 + np.exp(10.0 * (t - t_est - 0.3)))

    feed(tl, 1500, 50, position_pct=opening(1500, 50))  # above 90 %
    for first in range(2100, 4500, 100):  # below 10 %, 550 samples lost before
        feed(tl, first, 100, position_pct=opening(first, 100), lost_before=550 * (first == 2100))
    valve = [f for f in rec.faults if f[0] == "valve"]
    assert len(valve) == 1, rec.faults
    assert "passed its 10-90 % band with 0 sample(s) inside it" in valve[0][1] and "stuck" not in valve[0][1]
    assert [op.t for op in ops if isinstance(op, Trigger)] == [t_est]
    assert any(f[2] == "samples_lost" for f in rec.faults)


def test_a_restarted_stream_is_estimated_from_its_own_blocks_only():
    """After a restart the lost count is an estimate: the blocks before it say nothing of the new
    axis, so the trigger is estimated from the blocks after it."""
    host = ManualClock()
    tl, *_ = make(host=host)
    for i in range(5):
        feed(tl, 100 * i, 100, host)  # on time: device sample 499 at host 0.5
    # restarted: 300 samples estimated lost; its blocks arrive 0.5 s of samples later than on time
    for i in range(8, 15):
        feed(tl, 100 * i, 100, host, arrival=(100 * i + 100) / FS + 0.5, restarted=(i == 8), lost_before=300 * (i == 8))
    host.set(2.0)
    assert tl.mark_trigger() == pytest.approx(2.0 - 0.5 - 1.0, abs=1.5 / FS)  # with the blocks before it: 1.0


def test_a_stroke_after_the_estimates_window_is_measured_not_missing():
    """The TRIGGER reached the actuator late (a loaded host: at the fast clock 0.2 s of host time is 2.4 s of the
    axis) and its reply came back at axis 3.0: the stroke starts 2.5 s after the estimate, after the estimate's
    window. The feedback is watched until a window after the reply: the trigger is measured from it, and the
    window and the record follow it (they used to close on the estimate: "no stroke seen", the record cut)."""
    host = ManualClock()
    tl, rec, ops, closed, _ = make(host=host)  # 1 s pretrigger, 2 s window, 3 s record; manoeuvre beta 10, gamma 0
    for i in range(15):
        feed(tl, 100 * i, 100, host)
    t_est = tl.mark_trigger()
    host.set(4.0)
    assert tl.commit_trigger()  # the reply: host 4.0 s, sample 4000, axis 3.0
    stroke = 3.0
    for i in range(15, 70):
        t = (100 * i + np.arange(100) - 1000) / FS
        feed(tl, 100 * i, 100, position_pct=100.0 / (1.0 + np.exp(10.0 * (t - stroke))))
    triggers = [op.t for op in ops if isinstance(op, Trigger)]
    assert triggers[0] == t_est and triggers[-1] == pytest.approx(stroke, abs=2e-3)
    assert not any("no stroke seen" in f[1] for f in rec.faults), rec.faults
    assert closed == [(2.0, True)] and rec.ends == [("completed", "")]
    r = tl.fit_window(2.0)
    assert r.trigger_time_s == triggers[-1] and r.t[-1] == pytest.approx(triggers[-1] + 2.0, abs=2e-3)
    assert tl.counters().n_written == pytest.approx(1000 + (stroke + 3.0) * FS, abs=2)  # the record follows it


def test_the_steady_head_is_the_fit_paths_baseline_mean():
    host = ManualClock()
    tl, *_ = make(pretrigger_s=5.0, host=host)
    rng = np.random.default_rng(1)
    heads = 30.0 + rng.normal(0, 0.01, 5000)
    heads[:1000] += 5.0  # more than the baseline's length before the trigger: not in it
    for i in range(50):
        feed(tl, 100 * i, 100, host, head_m=heads[100 * i:100 * i + 100])
    tl.mark_trigger()
    t = (np.arange(5000) - 5000) / FS
    assert tl.steady_head(None) == pytest.approx(steady_head(t, heads, 0.0, np.nan, FS), abs=1e-12)
    assert tl.steady_head(None) == pytest.approx(30.0, abs=0.002)


def test_no_baseline_yet_is_the_fallback():
    tl, *_ = make()
    assert tl.steady_head(12.0) == 12.0


# ---------------------------------------------------------------- several sections (the rig's other transducers)

MID = TransducerChannel("mid", 41.032, "pressure_2", "head_mid")


def test_every_transducer_is_recorded_in_its_own_channels():
    tl, rec, ops, _, _ = make(others=(MID,))
    feed(tl, 0, 100, head_m=30.0, others={"pressure_2": 31.5})
    (a,) = [op for op in ops if isinstance(op, Append)]
    assert {"head_mid", "pressure_mid", "pressure_raw_mid", "pressure_quality_mid"} <= set(a.channels)
    assert a.channels["head_mid"] == pytest.approx(np.full(100, 31.5)) and a.channels["head"][0] == pytest.approx(30.0)
    assert a.channels["pressure_mid"] == pytest.approx(head_to_pressure_pa(np.full(100, 31.5)))
    assert not rec.faults and not rec.ends


def test_the_steady_head_and_the_ceiling_are_the_valves_transducers():
    tl, rec, _, _, _ = make(ceiling=50.0, others=(MID,))
    feed(tl, 0, 100, head_m=30.0, others={"pressure_2": 60.0})  # mid above the ceiling: not watched
    assert not rec.ends and tl.steady_head(None) == pytest.approx(30.0)
    assert tl.counters().peak == pytest.approx(30.0)


def test_a_flagged_transducer_before_the_trigger_aborts_naming_it():
    tl, rec, _, _, _ = make(others=(MID,))
    codes = np.zeros((100, 3), np.uint8)
    codes[70:, 2] = 7  # 22 mA on the mid transducer: a sensor fault
    feed(tl, 0, 100, codes=codes, others={"pressure_2": 31.0})
    (who, message, kind, extra), = rec.faults
    assert who == "pressure" and kind == "quality" and extra["transducer"] == "mid" and extra["channel"] == "pressure_2"
    assert message.startswith("pressure_2 (transducer mid) samples flagged from t = -0.930 s: sensor_fault")
    assert tl.counters().flagged == 30
    assert rec.ends == [("aborted", "pressure transducer 'mid' (pressure_2) fault before the trigger (sensor_fault): "
                                    "manoeuvre cancelled")]


def test_a_flagged_transducer_after_the_trigger_is_said_once_and_shortens_every_sections_window():
    host = ManualClock()
    tl, rec, _, closed, _ = make(duration_s=4.0, fit_window_s=3.0, others=(MID,), host=host)
    for i in range(15):
        feed(tl, 100 * i, 100, host, others={"pressure_2": 31.0})
    t0 = tl.mark_trigger()
    tl.commit_trigger()
    for i in range(15, 55):
        codes = np.zeros((100, 3), np.uint8)
        if i in (40, 41):  # 2.5 s after the trigger (the valve stays open: the trigger stays the estimate)
            codes[:, 2] = 6
        feed(tl, 100 * i, 100, codes=codes, others={"pressure_2": 31.0 + 0.001 * i})
    stuck = [f for f in rec.faults if f[2] == "stuck"]
    assert len(stuck) == 1 and stuck[0][3]["transducer"] == "mid"  # once per channel and code
    assert closed == [(3.0, True)] and rec.ends[-1] == ("completed", "")
    r = tl.fit_window(3.0)
    assert t0 == pytest.approx(0.5) and r.window_s == pytest.approx(2.5)  # the clean part before the stuck samples
    assert "shortened to 2.50 s" in r.note
    assert set(r.section_heads) == {"mid"} and r.section_heads["mid"].shape == r.head.shape == r.t.shape
    after = r.t >= t0
    assert r.section_heads["mid"][after][0] == pytest.approx(31.015)  # the block at 1.5 s on the run's axis


def test_a_slow_reading_is_stamped_with_the_devices_axis_through_a_stall_of_the_processing():
    """velab.recording.slow stamps a reading with ``device_axis``: the sample the device makes now (the block that
    waited least, plus the samples since), not the last sample processed (``now_axis``), which a stall of the
    processing holds back (a loaded host: readings seconds off their host instant)."""
    host = ManualClock()
    tl, *_ = make(host=host)
    for i in range(5):  # on time: block i's last sample made at host (100 i + 100) / FS
        feed(tl, 100 * i, 100, host)
    assert tl.device_axis == pytest.approx(tl.now_axis, abs=1.5 / FS)
    host.set(1.3)  # 0.8 s of host time and no block processed: the device is at its sample 1300
    assert tl.now_axis == pytest.approx(-0.5)
    assert tl.device_axis == pytest.approx(0.3, abs=1.5 / FS)


def test_the_samples_host_times_are_spaced_at_the_hosts_sample_rate():
    """Within a block the samples' host times step by 1 / (rate x the clock's scale): on a simulated rig's fast
    clock they come that much faster than the device's rate says (the run file's host_time)."""
    scale = 12.0
    host = ManualClock()
    tl, _, ops, _, _ = make(host=host, clock_scale=scale)
    feed(tl, 0, 100, host, arrival=0.1 / scale, host_time_s=1000.0)
    (append,) = [op for op in ops if isinstance(op, Append)]
    steps = np.diff(append.channels["host_time"])
    assert append.channels["host_time"][-1] == 1000.0 and steps == pytest.approx(1.0 / (FS * scale))
