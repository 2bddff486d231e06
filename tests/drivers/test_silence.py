"""velab.drivers.silence: a data timeout counts the time a reader listened, not the time its host held it."""

from __future__ import annotations

import pytest

from velab.drivers.silence import HELD_PASS_S, Silence


def test_silence_counts_each_pass_of_the_read_loop_up_to_its_cap():
    now = [0.0]
    s = Silence(0.25, clock=lambda: now[0])
    for _ in range(10):  # a silent device: passes of a poll period, all counted
        now[0] += 0.05
        s.passed()
    assert s.silent_s == pytest.approx(0.5)
    now[0] += 3.0  # the host held the reader: a pass counts its cap
    assert s.passed() == pytest.approx(0.75)
    s.reset()
    now[0] += 0.1
    assert s.passed() == pytest.approx(0.1)


def test_the_cap_covers_a_read_s_own_wait():
    assert Silence.for_wait(0.05).cap_s == HELD_PASS_S
    assert Silence.for_wait(0.2).cap_s == pytest.approx(0.4)
