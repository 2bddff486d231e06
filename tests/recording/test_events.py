"""velab.recording.events: the bounded event queue keeps phases, faults and the summary."""

from __future__ import annotations

import queue

import pytest

from velab.recording.events import EventQueue
from velab.recording.types import RecorderEvent


def ev(kind, data=None):
    return RecorderEvent(kind, 0.0, data)


def test_a_full_queue_drops_live_events_and_keeps_the_others():
    q = EventQueue(maxsize=3)
    for e in (ev("samples", 1), ev("phase", "armed"), ev("samples", 2)):
        q.offer(e)
    q.offer(ev("samples", 3))  # live, full: dropped
    q.offer(ev("fault", "x"))  # not live: the oldest live one makes room
    assert [(e.kind, e.data) for e in (q.get_nowait(), q.get_nowait(), q.get_nowait())] == \
        [("phase", "armed"), ("samples", 2), ("fault", "x")]
    assert q.dropped == 2 and q.empty()


def test_with_no_live_event_the_oldest_goes():
    q = EventQueue(maxsize=2)
    for k in ("phase", "fault", "done"):
        q.offer(ev(k))
    assert [q.get_nowait().kind, q.get_nowait().kind] == ["fault", "done"]


def test_the_queue_verbs():
    q = EventQueue(maxsize=1)
    q.put_nowait(ev("phase"))
    with pytest.raises(queue.Full):
        q.put_nowait(ev("phase"))
    assert q.qsize() == 1 and q.get(timeout=0.01).kind == "phase"
    with pytest.raises(queue.Empty):
        q.get(timeout=0.01)
