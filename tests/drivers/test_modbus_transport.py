"""The byte transports under the Modbus client, on a real loopback socket and a real pty.

A reply that arrived before the reader woke (a busy host descheduled it past its deadline) is taken,
not reported as a silent device; with nothing there, a late reader returns at once.
"""

import os
import select
import socket
import time

import pytest

from velab.drivers.modbus_transport import SerialTransport, TcpTransport

REPLY = bytes(range(1, 12))


def _until(cond, timeout_s=5.0):
    end = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < end, "state not reached"
        time.sleep(0.001)


def test_tcp_a_reply_already_received_is_taken_after_the_deadline():
    with socket.create_server(("127.0.0.1", 0)) as server:
        t = TcpTransport("127.0.0.1", server.getsockname()[1])
        t.open()
        peer, _ = server.accept()
        try:
            late = time.monotonic() - 1.0  # the reader woke a second after its deadline
            t0 = time.monotonic()
            assert t.read(len(REPLY), late) == b""  # nothing there: at once, not a wait
            assert time.monotonic() - t0 < 0.5
            peer.sendall(REPLY)
            _until(t.pending)
            assert t.read(len(REPLY), late) == REPLY
            t.write(b"\x01\x02")  # the socket is usable for the next request
            assert peer.recv(2) == b"\x01\x02"
        finally:
            peer.close()
            t.close()


def test_serial_a_reply_already_received_is_taken_after_the_deadline():
    master, slave = os.openpty()
    t = SerialTransport(os.ttyname(slave))
    try:
        t.open()
        late = time.monotonic() - 1.0
        assert t.read(len(REPLY), late) == b""
        os.write(master, REPLY)
        _until(lambda: select.select([slave], [], [], 0)[0])  # arrived on the line (not read)
        assert t.read(len(REPLY), late) == REPLY
    finally:
        t.close()
        os.close(master)
        os.close(slave)
