"""Test helpers for drivers: a PyMeasure-style ``expected_protocol`` byte transport.

    with expected_protocol([(b"\\x01\\x03\\x0b\\xba\\x00\\x02\\xe7\\xd6", b"\\x01\\x03\\x04...")]) as t:
        bus = ModbusClient(t, "rtu", unit=1)
        ...

Each pair is (bytes the driver must write, bytes the device answers). A reply of
``None`` (or b"") is a silent device: reads return nothing and the driver times out.
``Late(data)`` is a reply that arrives only after the driver gave up waiting (its
read came back empty at the deadline); ``Late(data, with_next=True)`` arrives just
before the *next* exchange's reply (a late reply glued to the next answer).
``Trickle(((delay_s, data), ...))`` arrives in pieces, each ``delay_s`` after the write
(a slave answering a backlog, a USB adapter's latency timer).
Writing anything unexpected fails the test with both byte strings shown.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass
from typing import Iterable


@dataclass(frozen=True)
class Late:
    data: bytes
    with_next: bool = False


@dataclass(frozen=True)
class Trickle:
    pieces: tuple  # ((delay_s after the write, bytes), ...)


class ExpectedProtocolTransport:
    name = "expected-protocol"
    char_time_s = 0.0

    def __init__(self, pairs: Iterable[tuple[bytes, bytes | Late | None]]):
        self.pairs = list(pairs)
        self.index = 0
        self._rx = bytearray()
        self._late: bytes = b""  # arrives when the driver's next read times out
        self._glued: bytes = b""  # arrives in front of the next exchange's reply
        self._coming: list = []  # (monotonic arrival, bytes) of Trickle pieces
        self._open = False
        self.opens = 0
        self.discarded = bytearray()  # every byte the driver threw away (flush / resync)

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
        if self._glued:
            self._rx += self._glued
            self._glued = b""
        if isinstance(reply, Trickle):
            now = time.monotonic()
            self._coming = sorted(self._coming + [(now + dt, bytes(b)) for dt, b in reply.pieces])
        elif isinstance(reply, Late):
            if reply.with_next:
                self._glued = reply.data
            else:
                self._late = reply.data
        elif reply:
            self._rx += reply

    def _arrive(self) -> None:
        now = time.monotonic()
        while self._coming and self._coming[0][0] <= now:
            self._rx += self._coming.pop(0)[1]

    def read(self, n: int, deadline: float) -> bytes:
        self._arrive()
        if not self._rx and self._coming and self._coming[0][0] <= deadline:
            time.sleep(max(0.0, self._coming[0][0] - time.monotonic()))
            self._arrive()
        if not self._rx:
            # a silent device: wait out the (short, test-chosen) deadline
            time.sleep(max(0.0, deadline - time.monotonic()))
            if self._late:  # ... and then the late reply comes in
                self._rx += self._late
                self._late = b""
            return b""
        out = bytes(self._rx[:n])
        del self._rx[:n]
        return out

    def pending(self) -> bool:
        self._arrive()
        return bool(self._rx)

    def discard_input(self) -> int:
        self._arrive()
        n = len(self._rx)
        self.discarded += self._rx
        self._rx.clear()
        return n

    def assert_done(self) -> None:
        assert self.index == len(self.pairs), f"only {self.index} of {len(self.pairs)} exchanges happened"


@contextlib.contextmanager
def expected_protocol(pairs):
    t = ExpectedProtocolTransport(pairs)
    t.open()
    yield t
    t.assert_done()
