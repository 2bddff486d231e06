"""The streaming ADC driver against its simulator over a real pty and over
socket:// on 127.0.0.1: data integrity, and every injected fault ending in a
typed error, a quality flag or an exactly counted gap (never a hang)."""

from __future__ import annotations

import math
import socket
import time

import numpy as np
import pytest

from sim_helpers import stream_profile

from velab.drivers.base import DeviceDisconnected, DeviceException, DeviceTimeout, Quality
from velab.drivers.streaming_adc import RAW_FULL_SCALE, StreamingADC
from velab.simulators.streaming_adc import FaultPlan, StreamingADCSimulator, ramp_source

pytestmark = pytest.mark.timeout(60)

ALL4 = ["pressure", "valve_position", "spare_2", "spare_3"]


profile = stream_profile


@pytest.fixture(params=["pty", "tcp"])
def transport(request):
    return request.param


def serve(sim, transport):
    return sim.serve_pty() if transport == "pty" else sim.serve_tcp()


def collect(adc, n_samples, timeout=20.0):
    blocks, deadline = [], time.monotonic() + timeout
    while sum(b.n for b in blocks) < n_samples:
        assert time.monotonic() < deadline, "stream too slow"
        blocks.append(adc.get_block(timeout=5))
    return blocks


def expected_counts(idx, channels, rate=10_000):
    sig = ramp_source(np.asarray(idx) / rate)[:, channels]
    return np.rint(sig * (RAW_FULL_SCALE / 25.0)).astype(np.int16)


def test_stream_integrity(transport):
    with StreamingADCSimulator(ramp_source, realtime=False) as sim:
        url = serve(sim, transport)
        with StreamingADC(url, profile()) as adc:
            assert adc.identify().startswith("VELAB,SADC-4,")
            cfg = adc.configure(10_000, ALL4, block_samples=50)
            assert cfg.rate_hz == 10_000
            adc.start()
            blocks = collect(adc, 20_000)
            stats = adc.stop()
        raw = np.concatenate([b.raw for b in blocks])
        idx = np.concatenate([b.first_index + np.arange(b.n) for b in blocks])
        np.testing.assert_array_equal(idx, np.arange(idx.size))  # contiguous, in order
        np.testing.assert_array_equal(raw, expected_counts(idx, [0, 1, 2, 3]))  # every count exact
        assert all(b.lost_before == 0 and b.quality == (Quality.OK,) * 4 for b in blocks)
        # what the device made = what we got (stream + tail after STOP)
        assert stats.lost == 0 and stats.crc_errors == 0
        # (fast mode keeps streaming until stop(); blocks the test did not take overflow the queue, counted)
        assert stats.samples + stats.queue_dropped == sim.stats.last_stop_total == sim.stats.samples_generated


def test_realtime_pacing_with_baud_and_one_channel():
    with StreamingADCSimulator(ramp_source, realtime=True, baud=115_200) as sim:
        url = sim.serve_tcp()
        with StreamingADC(url, profile()) as adc:
            adc.configure(1000, ["pressure"], block_samples=10)
            adc.start()
            blocks = collect(adc, 300)
            stats = adc.stop()
        assert stats.lost == 0 and stats.samples + stats.queue_dropped == sim.stats.samples_generated
        b = blocks[-1]
        np.testing.assert_allclose(b.device_time_s, (b.first_index + np.arange(b.n)) / 1000)


def test_link_too_slow_is_refused():
    with StreamingADCSimulator(realtime=True, baud=9600) as sim:
        with StreamingADC(sim.serve_tcp(), profile()) as adc:
            adc.configure(10_000, ALL4)
            with pytest.raises(DeviceException) as ei:
                adc.start()
            assert ei.value.code == 5


def test_bad_argument_and_busy_from_the_device():
    with StreamingADCSimulator(realtime=False) as sim:
        url = sim.serve_tcp()
        with StreamingADC(url, profile()) as adc:
            with pytest.raises(DeviceException) as ei:
                adc.command("RATE 5")
            assert ei.value.code == 2
            with pytest.raises(DeviceException) as ei:
                adc.command("CHAN 0,0")
            assert ei.value.code == 2
            with pytest.raises(DeviceException) as ei:
                adc.command("LASER ON")
            assert ei.value.code == 1
            with pytest.raises(DeviceException) as ei:
                adc.command("X" * 80)
            assert ei.value.code == 4
        # raw socket: a command while streaming gets ERR 3 between frames
        host, port = url[len("socket://"):].split(":")
        with socket.create_connection((host, int(port)), timeout=5) as s:
            s.sendall(b"START\n")
            time.sleep(0.05)
            s.sendall(b"RATE 1000\n")
            buf, deadline = b"", time.monotonic() + 5
            while b"ERR 3 BUSY" not in buf and time.monotonic() < deadline:
                buf += s.recv(65536)
            assert b"ERR 3 BUSY" in buf


FAULTS = FaultPlan(corrupt_every=37, drop_every=53, drop_bytes_every=41, garbage_every=29,
                   overrun_at=frozenset({100, 400}), overrun_frames=7, seed=5)


@pytest.mark.parametrize("nch", [1, 4])
def test_faults_counted_exactly(transport, nch):
    with StreamingADCSimulator(ramp_source, realtime=False, faults=FAULTS) as sim:
        url = serve(sim, transport)
        # unpaced (realtime=False): the device sends as fast as the host takes, so STOP's reply comes behind all
        # that is in the socket by then, which a loaded host read in more than the usual 1 s
        with StreamingADC(url, profile(command_timeout_s=5.0)) as adc:
            adc.configure(10_000, ALL4[:nch], block_samples=20)
            adc.start()
            blocks = collect(adc, 20_000)
            stats = adc.stop()
        s = sim.stats
        assert s.frames_corrupted and s.frames_dropped and s.frames_bytes_dropped and s.frames_overrun
        assert stats.lost == s.samples_lost  # exact, from the device's counter
        assert stats.samples + stats.queue_dropped + stats.lost == s.last_stop_total
        assert stats.crc_errors > 0 and stats.resyncs > 0 and stats.overruns == 2
        assert 0 < sum(b.lost_before for b in blocks) <= stats.lost
        # nothing invented: every delivered count is the source's value at its index
        raw = np.concatenate([b.raw for b in blocks])
        idx = np.concatenate([b.first_index + np.arange(b.n) for b in blocks])
        np.testing.assert_array_equal(raw, expected_counts(idx, list(range(nch))))
        assert any(b.overrun for b in blocks)


def test_silent_device_is_timeout(transport):
    with StreamingADCSimulator(realtime=False, faults=FaultPlan(silent_after_frames=30)) as sim:
        url = serve(sim, transport)
        adc = StreamingADC(url, profile(data_timeout_s=0.5, command_timeout_s=0.3))
        adc.configure(10_000, ["pressure"], block_samples=10)
        adc.start()
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout):
            while True:
                adc.get_block(timeout=5)
        assert time.monotonic() - t0 < 10
        assert isinstance(adc.error, DeviceTimeout)
        adc.close()


def test_disconnect_reconnects_and_reports_gap(transport):
    plan = FaultPlan(disconnect_after_frames=200, reconnect_delay_s=0.3)
    with StreamingADCSimulator(ramp_source, realtime=True, faults=plan) as sim:
        url = serve(sim, transport)
        with StreamingADC(url, profile()) as adc:
            adc.configure(10_000, ["pressure", "valve_position"], block_samples=50)
            adc.start()
            blocks = []
            deadline = time.monotonic() + 20
            while not any(b.segment == 1 for b in blocks) or sum(b.n for b in blocks if b.segment == 1) < 500:
                assert time.monotonic() < deadline
                blocks.append(adc.get_block(timeout=5))
            stats = adc.stop()
        assert stats.reconnects == 1 and sim.stats.disconnects == 1
        first_new = next(b for b in blocks if b.segment == 1)
        assert first_new.restarted and first_new.first_index == 0
        assert first_new.lost_before > 0 and stats.lost_estimated == first_new.lost_before
        # the old segment is contiguous and nothing is interpolated across the gap
        old = [b for b in blocks if b.segment == 0]
        assert sum(b.n for b in old) <= 200 * 50
        assert stats.lost == 0


def test_disconnect_without_reconnect_is_typed_error():
    plan = FaultPlan(disconnect_after_frames=50, reconnect_delay_s=0.2)
    with StreamingADCSimulator(realtime=False, faults=plan) as sim:
        adc = StreamingADC(sim.serve_tcp(), profile(reconnect=False))
        adc.configure(10_000, ["pressure"], block_samples=10)
        adc.start()
        with pytest.raises(DeviceDisconnected):
            while True:
                adc.get_block(timeout=5)
        adc.close()


def test_reconnect_gives_up_after_timeout():
    plan = FaultPlan(disconnect_after_frames=50, reconnect_delay_s=30)
    with StreamingADCSimulator(realtime=False, faults=plan) as sim:
        adc = StreamingADC(sim.serve_tcp(), profile(reconnect_timeout_s=1.0, command_timeout_s=0.2))
        adc.configure(10_000, ["pressure"], block_samples=10)
        adc.start()
        t0 = time.monotonic()
        with pytest.raises(DeviceDisconnected, match="could not reconnect"):
            while True:
                adc.get_block(timeout=5)
        assert time.monotonic() - t0 < 10
        adc.close()


def test_input_faults_become_quality_flags():
    nan_ch = (0, 0.010, 0.012, math.nan)
    clipped = (1, 0.020, 0.021, 30.0)  # beyond the 25 mA range: clipped at full scale, NE43 sensor fault
    open_loop = (0, 0.030, 0.031, 1.0)
    over = (0, 0.040, 0.041, 20.4)  # above the span, inside NE43: a measurement (a bound)
    plan = FaultPlan(input_faults=(nan_ch, clipped, open_loop, over))
    with StreamingADCSimulator(ramp_source, realtime=False, faults=plan) as sim:
        with StreamingADC(sim.serve_tcp(), profile()) as adc:
            adc.configure(10_000, ["pressure", "valve_position"], block_samples=10)
            adc.start()
            blocks = collect(adc, 500)
            adc.stop()
    t = np.concatenate([b.device_time_s for b in blocks])
    values = np.concatenate([b.values for b in blocks])
    raw = np.concatenate([b.raw for b in blocks])
    in_nan = (t >= 0.010 - 1e-9) & (t < 0.012 - 1e-9)
    assert np.isnan(values[in_nan, 0]).all() and not np.isnan(values[~in_nan]).any()
    assert (raw[(t >= 0.020 - 1e-9) & (t < 0.021 - 1e-9), 1] == RAW_FULL_SCALE).all()

    def block_at(ts):
        return next(b for b in blocks if b.first_index <= round(ts * 10_000) < b.next_index)

    assert block_at(0.010).quality[0] is Quality.NAN and block_at(0.010).flags & 0x04
    assert block_at(0.020).quality[1] is Quality.SENSOR_FAULT
    assert block_at(0.030).quality[0] is Quality.OPEN_LOOP
    assert block_at(0.040).quality[0] is Quality.OVER_RANGE
    # per sample: exactly the faulted samples are not measurements, nothing else
    good = np.concatenate([b.good(0) for b in blocks])
    bad_window = in_nan | ((t >= 0.030 - 1e-9) & (t < 0.031 - 1e-9))
    np.testing.assert_array_equal(good, ~bad_window)


def test_callback_mode_and_restart():
    with StreamingADCSimulator(realtime=False) as sim:
        with StreamingADC(sim.serve_pty(), profile()) as adc:
            adc.configure(5000, ["pressure"])
            for _ in range(2):
                got = []
                adc.start(callback=got.append)
                deadline = time.monotonic() + 10
                while sum(b.n for b in got) < 5000 and time.monotonic() < deadline:
                    time.sleep(0.01)
                stats = adc.stop()
                assert stats.samples >= 5000 and stats.lost == 0
                assert got[0].first_index == 0


def test_with_simulated_rig():
    rig_mod = pytest.importorskip("velab.simulators.rig")
    from velab.config import load_material, load_rig
    from velab.simulators.clock import ManualClock

    clock = ManualClock()
    rig = rig_mod.SimulatedRig(load_rig("perugia"), load_material("A"), clock)
    with StreamingADCSimulator(rig.analog_inputs, realtime=False, clock=clock) as sim:
        with StreamingADC(sim.serve_tcp(), profile()) as adc:
            adc.configure(10_000, ["pressure", "valve_position"], block_samples=50)
            adc.start()
            blocks = collect(adc, 2000)
            adc.stop()
    b = blocks[0]
    expected = rig.analog_inputs(b.device_time_s)[:, :2]
    np.testing.assert_allclose(b.signal, expected, atol=25.0 / RAW_FULL_SCALE)  # within one count
    assert b.quality == (Quality.OK, Quality.OK)


def test_registered_in_simulated_bench():
    bench_mod = pytest.importorskip("velab.simulators.bench")
    with bench_mod.SimulatedBench.from_config("default", ephemeral=True) as sim:
        for tr in ("socket", "pty"):
            ep = sim.endpoint("streaming_adc", tr)
            assert ep.kind == "streaming_adc"
            with StreamingADC(ep.link or ep.address, profile()) as adc:
                adc.configure(10_000, ["pressure", "valve_position"])
                adc.start()
                b = adc.get_block(timeout=5)
                adc.stop()
            head = b.head_m("pressure")
            assert b.quality == (Quality.OK, Quality.OK)
            assert abs(np.median(head) - sim.rig.rig.steady_head_m) < 1.0  # steady state before a trigger
