"""Test helpers for drivers: a PyMeasure-style ``expected_protocol`` byte transport.

    with expected_protocol([(b"\\x01\\x03\\x0b\\xba\\x00\\x02\\xe7\\xd6", b"\\x01\\x03\\x04...")]) as t:
        bus = ModbusClient(t, "rtu", unit=1)
        ...

Each pair is (bytes the driver must write, bytes the device answers). A reply of
``None`` (or b"") is a silent device: reads return nothing and the driver times out.
Writing anything unexpected fails the test with both byte strings shown.
"""

from __future__ import annotations

import contextlib
import time
from typing import Iterable


class ExpectedProtocolTransport:
    name = "expected-protocol"

    def __init__(self, pairs: Iterable[tuple[bytes, bytes | None]]):
        self.pairs = list(pairs)
        self.index = 0
        self._rx = bytearray()
        self._open = False
        self.opens = 0

    @property
    def is_open(self) -> bool:
        return self._open

    def open(self) -> None:
        self._open = True
        self.opens += 1

    def close(self) -> None:
        self._open = False

    def write(self, data: bytes) -> None:
        if self.index >= len(self.pairs):
            raise AssertionError(f"unexpected write {bytes(data).hex(' ')}: all {len(self.pairs)} exchanges done")
        expected, reply = self.pairs[self.index]
        if bytes(data) != bytes(expected):
            raise AssertionError(
                f"exchange {self.index}: wrote {bytes(data).hex(' ')}, expected {bytes(expected).hex(' ')}"
            )
        self.index += 1
        if reply:
            self._rx += reply

    def read(self, n: int, deadline: float) -> bytes:
        if not self._rx:
            # a silent device: wait out the (short, test-chosen) deadline
            time.sleep(max(0.0, deadline - time.monotonic()))
            return b""
        out = bytes(self._rx[:n])
        del self._rx[:n]
        return out

    def discard_input(self) -> None:
        self._rx.clear()

    def assert_done(self) -> None:
        assert self.index == len(self.pairs), f"only {self.index} of {len(self.pairs)} exchanges happened"


@contextlib.contextmanager
def expected_protocol(pairs):
    t = ExpectedProtocolTransport(pairs)
    t.open()
    yield t
    t.assert_done()
