"""velab.drivers.pressure_source: both ADCs behind one verb set, each tested alone on a fake driver
(no sockets, no clock): what is a block, what is a transient error, what is fatal."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from stage_helpers import block
from velab.drivers.base import DeviceDisconnected, DeviceError, DeviceTimeout
from velab.drivers.pressure_source import BufferedSource, StreamingSource, pressure_source


def _channel(name, index, units):
    return SimpleNamespace(name=name, index=index, calibration=SimpleNamespace(units=units))


# an ADC wired for several sections: the valve's transducer, the valve position, two more transducers
WIRED = (_channel("pressure", 0, "Pa"), _channel("valve_position", 1, "%"), _channel("pressure_2", 2, "Pa"),
         _channel("pressure_3", 3, "Pa"))


class FakeStreaming:
    """The StreamingADC's queue verbs: get_block raises what the script says, get_blocks the rest."""

    def __init__(self, script):
        self.script, self.error, self.calls = list(script), None, []
        self.profile = SimpleNamespace(channels=WIRED, enabled=("pressure", "valve_position"))

    def get_block(self, timeout=None):
        item = self.script.pop(0)
        if isinstance(item, BaseException):
            raise item
        return item

    def get_blocks(self):
        out = []
        while self.script and not isinstance(self.script[0], BaseException):
            out.append(self.script.pop(0))
        return out

    def start(self, wait_when_full=False):
        self.calls.append(("start", wait_when_full))

    def configure(self, rate, chans, block):
        self.calls.append(("configure", rate, tuple(chans), block))
        return SimpleNamespace(rate_hz=rate * 1.0000001)

    def stop(self):
        self.calls.append(("stop",))


class FakeBuffered:
    def __init__(self, script, rate=1000.0):
        self.script, self.rate, self.calls = list(script), rate, []
        self.sample_rate_hz = None
        self.channels = list(WIRED)
        self.density_kg_m3 = 998.2

    def channel(self, name):
        return next(c for c in self.channels if c.name == name)

    def read_channels(self):
        self.calls.append(("read_channels",))
        return {c.name: SimpleNamespace(value=98066.5 * (1 + c.index), quality=SimpleNamespace(value="ok"))
                for c in self.channels}

    def read_buffer(self):
        item = self.script.pop(0)
        if isinstance(item, BaseException):
            raise item
        return item

    def stop_buffer(self):
        self.calls.append(("stop_buffer",))

    def configure_buffer(self, rate, n):
        self.calls.append(("configure_buffer", rate, n))

    def start_buffer(self):
        self.calls.append(("start_buffer",))
        self.sample_rate_hz = self.rate


def test_a_streaming_read_takes_every_queued_block():
    b1, b2, b3 = block(0, 5), block(5, 5), block(10, 5)
    src = StreamingSource(FakeStreaming([b1, b2, b3]), "adc")
    r = src.read_blocks()
    assert r.blocks == (b1, b2, b3) and not r.error


def test_a_streaming_timeout_is_no_data_unless_the_reader_gave_up():
    adc = FakeStreaming([DeviceTimeout("nothing"), DeviceTimeout("nothing")])
    src = StreamingSource(adc, "adc")
    assert src.read_blocks().blocks == ()
    assert "silent, frozen or reconnecting" in src.stall_hint()
    adc.error = DeviceDisconnected("adc: gone")
    with pytest.raises(DeviceError, match="gone"):
        src.read_blocks()
    assert src.stall_hint() == ""


def test_any_other_streaming_error_is_fatal():
    src = StreamingSource(FakeStreaming([ValueError("bad frame")]), "adc")
    with pytest.raises(DeviceError, match="bad frame"):
        src.read_blocks()


def test_the_streaming_rate_is_the_devices_only_when_it_differs():
    adc = FakeStreaming([])
    src = StreamingSource(adc, "adc")
    src.configure(1000.0)
    assert src.start() == 1000.0  # 1e-7 relative: the asked rate
    assert adc.calls[0][:3] == ("configure", 1000.0, ("pressure", "valve_position"))
    assert adc.calls[1] == ("start", True)  # back-pressure reaches the device


def test_a_failed_poll_is_transient_and_an_empty_poll_no_data():
    b = block(0, 5)
    adc = FakeBuffered([DeviceTimeout("no reply"), block(5, 0), b])
    src = BufferedSource(adc, "adc")
    r = src.read_blocks()
    assert r.blocks == () and r.error == "no reply" and "buffer keeps the samples" in r.note
    assert src.read_blocks().blocks == ()
    assert src.read_blocks().blocks == (b,)


def test_a_poll_that_reports_a_gap_is_a_block_even_without_samples():
    gap = block(5, 0, lost_before=7)
    assert BufferedSource(FakeBuffered([gap]), "adc").read_blocks().blocks == (gap,)


def test_the_buffered_rate_is_the_modules_once_it_runs():
    adc = FakeBuffered([], rate=999.0)
    src = BufferedSource(adc, "adc")
    src.configure(1000.0)
    assert src.start() == 999.0
    assert [c[0] for c in adc.calls] == ["stop_buffer", "configure_buffer", "start_buffer"]
    assert adc.calls[1] == ("configure_buffer", 1000, 2)  # ch0 pressure, ch1 valve position


def test_the_streaming_source_acquires_every_transducer_asked_for_and_the_position():
    adc = FakeStreaming([])
    src = StreamingSource(adc, "adc")
    assert src.channels() == ("pressure", "valve_position")
    assert src.pressure_channels() == ("pressure", "pressure_2", "pressure_3")  # not only the profile's default list
    src.configure(1000.0, ("pressure", "pressure_3"))
    assert adc.calls[0][2] == ("pressure", "pressure_3", "valve_position")
    with pytest.raises(DeviceError, match="'valve_position' is not a pressure channel"):
        src.configure(1000.0, ("pressure", "valve_position"))


def test_the_buffered_source_records_up_to_the_highest_input_asked_for():
    adc = FakeBuffered([], rate=1000.0)
    src = BufferedSource(adc, "adc")
    assert src.pressure_channels() == ("pressure", "pressure_2", "pressure_3")
    src.configure(1000.0, ("pressure", "pressure_2"))  # the ring holds inputs 0..n-1: n = 3
    assert adc.calls[1] == ("configure_buffer", 1000, 3)
    adc.calls.clear()
    src.configure(1000.0, ("pressure", "pressure_3"))
    assert adc.calls[1] == ("configure_buffer", 1000, 4)


def test_a_buffered_look_reads_every_transducer_at_one_instant():
    adc = FakeBuffered([])
    looks = BufferedSource(adc, "adc").spot_heads(1000.0, ("pressure", "pressure_2"))
    assert adc.calls == [("read_channels",)]  # one polled read for all of them
    assert set(looks) == {"pressure", "pressure_2"} and looks["pressure_2"][1] == "ok"
    assert looks["pressure_2"][0] == pytest.approx(3 * looks["pressure"][0])


def test_only_an_adc_is_a_pressure_source():
    with pytest.raises(DeviceError, match="not a pressure source"):
        pressure_source(object(), "flowmeter")
