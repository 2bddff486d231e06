"""The null-modem pty bridge: bytes both ways, fault hook, wire time, pause."""

import time

import pytest
import serial

from sim_helpers import wait_until

from velab.simulators.pty_bridge import PtyPair


def open_port(path):
    return serial.Serial(path, 115200, timeout=5.0)  # (a read returns once its bytes are there)


def dropped(pair, n: int) -> int:
    """The bridge's count of bytes dropped towards the host once it is ``n`` (its last value after 5 s): the bytes
    written into a faulted or paused line are gone before the line is restored (on a loaded host the bridge's
    thread could read them only after, and forward them)."""
    return wait_until(lambda: pair.bytes_dropped["to_host"], n, timeout_s=5.0)


def test_bytes_flow_both_ways_and_fault_hook():
    with PtyPair() as pair:
        dev, host = open_port(pair.device_path), open_port(pair.host_path)
        try:
            host.write(b"\x01\x02\x0d\x0a")
            assert dev.read(4) == b"\x01\x02\x0d\x0a"  # raw: no CR/LF rewriting, no echo
            pair.fault("to_host", lambda b: b.replace(b"A", b"B"))
            dev.write(b"AAA")
            assert host.read(3) == b"BBB"
            pair.fault("to_host", lambda b: b"")
            dev.write(b"lost")
            assert dropped(pair, 4) == 4
            host.timeout = 0.1
            assert host.read(4) == b""
            pair.fault("to_host", None)
            dev.write(b"ok")
            host.timeout = 5.0  # (a loaded host: the bridge's thread may wait its turn)
            assert host.read(2) == b"ok"
            with pytest.raises(ValueError):
                pair.fault("sideways", None)
        finally:
            dev.close()
            host.close()


def test_wire_time_at_baud_rate():
    with PtyPair(baudrate=9600) as pair:
        dev, host = open_port(pair.device_path), open_port(pair.host_path)
        try:
            t0 = time.monotonic()
            host.write(bytes(96))
            assert len(dev.read(96)) == 96
            assert time.monotonic() - t0 >= 96 * 10 / 9600 * 0.9  # ~0.1 s on the wire
        finally:
            dev.close()
            host.close()


def test_pause_and_stop():
    pair = PtyPair().start()
    dev, host = open_port(pair.device_path), open_port(pair.host_path)
    host.timeout = 0.1
    pair.pause(True)
    dev.write(b"x")
    assert dropped(pair, 1) == 1
    assert host.read(1) == b""
    pair.pause(False)
    dev.write(b"y")
    host.timeout = 5.0  # (a loaded host: the bridge's thread may wait its turn)
    assert host.read(1) == b"y"
    assert pair.bytes_dropped == {"to_host": 1, "to_device": 0}
    dev.close()
    host.close()
    pair.stop()
