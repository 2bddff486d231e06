"""The simulated devices' Modbus server answers every request it receives, in order.

A request that arrives together with another (a client whose earlier request timed out while the
device was busy sends the next one; on a loaded host both reach the server in one read) is carried
out and answered like any other, as a real device's queue does: pymodbus alone drops it.
"""

import socket
import struct
import time

import pytest

from sim_helpers import wait_until
from velab.drivers.modbus import crc16
from velab.drivers.profile import load_profile
from velab.drivers.valve import Command, ValveState
from velab.simulators.bench import SimulatedBench
from velab.simulators.clock import ManualClock

UNIT = 3
CONFIG = {
    "rig": "perugia", "material": "A", "clock": "manual",
    "devices": {"valve": {"kind": "valve_actuator", "unit": UNIT,
                          "endpoints": [{"transport": "tcp"}, {"transport": "rtu-socket"}]}},
}
PROFILE = load_profile("valve_actuator")


@pytest.fixture(scope="module")
def sim():
    with SimulatedBench(CONFIG, clock=ManualClock(), ephemeral=True) as s:
        s.clock.advance(100.0)
        yield s


def _pdu_read(address: int, count: int) -> bytes:
    return struct.pack(">BHH", 3, address, count)


def _pdu_write(address: int, value: int) -> bytes:
    return struct.pack(">BHHBH", 16, address, 1, 2, value)


def _frames(transport: str, pdus: list[bytes]) -> bytes:
    if transport == "tcp":
        return b"".join(struct.pack(">HHHB", tid, 0, len(p) + 1, UNIT) + p for tid, p in enumerate(pdus, 1))
    return b"".join(bytes([UNIT]) + p + crc16(bytes([UNIT]) + p) for p in pdus)


def _replies(transport: str, sock: socket.socket, n: int) -> list[tuple[int, bytes]]:
    """(transaction id or 0, PDU) of the first n replies, within 3 s."""
    got, out, end = b"", [], time.monotonic() + 3.0
    while len(out) < n and time.monotonic() < end:
        try:
            chunk = sock.recv(4096)
        except socket.timeout:
            continue
        if not chunk:
            break
        got += chunk
        while True:
            if transport == "tcp":
                if len(got) < 7 or len(got) < 6 + struct.unpack(">H", got[4:6])[0]:
                    break
                size = 6 + struct.unpack(">H", got[4:6])[0]
                out.append((struct.unpack(">H", got[:2])[0], got[7:size]))
            else:
                if len(got) < 3:
                    break
                fc = got[1]
                size = (5 + got[2]) if fc == 3 else 8 if fc == 16 else 5
                if len(got) < size:
                    break
                assert crc16(got[:size - 2]) == got[size - 2:size], "reply CRC"
                out.append((0, got[1:size - 2]))
            got = got[size:]
    return out


@pytest.mark.parametrize("transport", ["tcp", "rtu-socket"])
def test_a_trigger_that_arrives_with_an_earlier_request_is_carried_out_and_answered(sim, transport):
    sim.rig.reset()
    settings = sim.bench(prefer=(transport,)).devices["valve"].settings
    host, port = (settings["host"], settings["port"]) if transport == "tcp" else \
        settings["port"].removeprefix("socket://").split(":")
    state, count, command = (PROFILE.reg(n).address for n in ("state", "trigger_count", "command"))
    with socket.create_connection((host, int(port)), timeout=0.2) as sock:
        sock.sendall(_frames(transport, [_pdu_write(command, int(Command.ARM))]))
        assert len(_replies(transport, sock, 1)) == 1
        assert wait_until(sim.rig.state, ValveState.ARMED) is ValveState.ARMED  # the profile computed
        count_before = sim.rig.trigger_count
        # a status read that (for its client) timed out, then the TRIGGER, then a read back: one read
        sock.sendall(_frames(transport, [_pdu_read(state, 1), _pdu_write(command, int(Command.TRIGGER)),
                                         _pdu_read(count, 1)]))
        replies = _replies(transport, sock, 3)
    assert [r[1][0] for r in replies] == [3, 16, 3], f"one reply per request, in order: {replies}"
    if transport == "tcp":
        assert [r[0] for r in replies] == [1, 2, 3]
    assert sim.rig.trigger_count == count_before + 1
    assert struct.unpack(">H", replies[2][1][2:4])[0] == (count_before + 1) & 0xFFFF, \
        "the read queued behind the TRIGGER sees it carried out"
