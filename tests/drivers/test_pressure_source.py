"""velab.drivers.pressure_source: both ADCs behind one verb set, each tested alone on a fake driver
(no sockets, no clock): what is a block, what is a transient error, what is fatal."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from stage_helpers import block
from velab.drivers.base import DeviceDisconnected, DeviceError, DeviceTimeout
from velab.drivers.pressure_source import BufferedSource, StreamingSource, pressure_source


class FakeStreaming:
    """The StreamingADC's queue verbs: get_block raises what the script says, get_blocks the rest."""

    def __init__(self, script):
        self.script, self.error, self.calls = list(script), None, []

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
        self.channels = [SimpleNamespace(name="pressure", calibration=SimpleNamespace(units="Pa"))]

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
    src.channels = lambda: ("pressure", "valve_position")
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
    assert adc.calls[1] == ("configure_buffer", 1000, 1)


def test_only_an_adc_is_a_pressure_source():
    with pytest.raises(DeviceError, match="not a pressure source"):
        pressure_source(object(), "flowmeter")
