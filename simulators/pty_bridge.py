"""A null-modem cable made of two pseudo-terminals (Linux), with fault and wire-time hooks.

    pair = PtyPair(baudrate=115200)        # baudrate=None: no wire time
    pair.start()
    server opens pair.device_path          # the simulated device's end
    client opens pair.host_path            # the end velab (or minimalmodbus...) opens
    pair.fault("to_host", lambda b: b[:-1] + bytes([b[-1] ^ 0xFF]))   # corrupt replies
    pair.fault("to_host", None)            # clear
    pair.pause(True)                       # silent line (cable pulled): bytes are dropped
    pair.stop()

Two ``pty.openpty()`` pairs; one thread per direction copies between the master
ends. Fault functions take the chunk of bytes just read and return what to
forward (b"" drops it). With a baud rate, each chunk is held for its time on the
wire, 10 bits per byte (8N1) by default. Reused by the streaming-ADC simulator.
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from typing import Callable

DIRECTIONS = ("to_host", "to_device")


class PtyPair:
    def __init__(self, baudrate: int | None = None, bits_per_byte: int = 10):
        self.baudrate = baudrate
        self.bits_per_byte = bits_per_byte
        self._faults: dict[str, Callable[[bytes], bytes] | None] = {d: None for d in DIRECTIONS}
        self._paused = False
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.bytes_copied = {d: 0 for d in DIRECTIONS}
        self.bytes_dropped = {d: 0 for d in DIRECTIONS}  # read from one end, not forwarded: paused, or by a fault
        self._dev_master, self._dev_slave = os.openpty()
        self._host_master, self._host_slave = os.openpty()
        for fd in (self._dev_slave, self._host_slave):
            tty.setraw(fd)
        self.device_path = os.ttyname(self._dev_slave)
        self.host_path = os.ttyname(self._host_slave)

    @property
    def char_time_s(self) -> float:
        return 0.0 if not self.baudrate else self.bits_per_byte / self.baudrate

    def fault(self, direction: str, fn: Callable[[bytes], bytes] | None) -> None:
        """Install (or clear, fn=None) a byte-fault function on one direction."""
        if direction not in DIRECTIONS:
            raise ValueError(f"direction must be one of {DIRECTIONS}, got {direction!r}")
        self._faults[direction] = fn

    def pause(self, paused: bool = True) -> None:
        """While paused, everything written on either side is dropped (a silent line)."""
        self._paused = paused

    def _pump(self, src: int, dst: int, direction: str) -> None:
        while not self._stop.is_set():
            try:
                r, _, _ = select.select([src], [], [], 0.05)
            except (OSError, ValueError):
                return
            if not r:
                continue
            try:
                data = os.read(src, 4096)
            except OSError:  # the other side closed: wait for a reopen
                time.sleep(0.01)
                continue
            if not data:
                continue
            if self._paused:
                self.bytes_dropped[direction] += len(data)
                continue
            if self.char_time_s:
                time.sleep(len(data) * self.char_time_s)
            fn = self._faults[direction]
            if fn is not None:
                n = len(data)
                data = fn(data)
                self.bytes_dropped[direction] += max(0, n - len(data))
            if data:
                try:
                    os.write(dst, data)
                    self.bytes_copied[direction] += len(data)
                except OSError:
                    pass

    def start(self) -> "PtyPair":
        if self._threads:
            return self
        self._stop.clear()
        self._threads = [
            threading.Thread(target=self._pump, args=(self._dev_master, self._host_master, "to_host"), daemon=True,
                             name="pty-to-host"),
            threading.Thread(target=self._pump, args=(self._host_master, self._dev_master, "to_device"), daemon=True,
                             name="pty-to-device"),
        ]
        for t in self._threads:
            t.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(1.0)
        self._threads = []
        for fd in (self._dev_master, self._dev_slave, self._host_master, self._host_slave):
            try:
                os.close(fd)
            except OSError:
                pass
        self._dev_master = self._dev_slave = self._host_master = self._host_slave = -1

    def __enter__(self) -> "PtyPair":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
