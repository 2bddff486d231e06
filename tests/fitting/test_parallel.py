"""velab.fitting.parallel: the fitter's one helper thread."""

import threading

from velab.fitting.parallel import both, map_each, map_pair


def _in_thread(fn, timeout_s=30.0):
    out = {}
    t = threading.Thread(target=lambda: out.setdefault("result", fn()), daemon=True)
    t.start()
    t.join(timeout_s)
    assert not t.is_alive(), "did not return"
    return out["result"]


def test_work_on_the_helper_that_splits_again_runs_there_in_turn():
    """Items handed to the helper (map_pair) whose own work splits in two (a time-domain polish's Jacobian
    columns inside a per-run job): the helper is busy, so their parts run in turn where they are. The
    helper waited for itself before: that call never returned."""
    names = []

    def inner(i):
        a, b = both(lambda: (i, threading.current_thread().name), lambda: (-i, threading.current_thread().name))
        names.append((a[1], b[1]))
        return a[0] + b[0] + 10 * i

    assert _in_thread(lambda: map_pair(lambda _, i: inner(i), list(range(6)), lambda: None)) == [10 * i for i in range(6)]
    assert len(names) == 6 and all(a == b for a, b in names)  # each call's two parts in one thread


def test_a_busy_helper_is_not_waited_for():
    """While the helper runs another fit's part, a second fit's split runs both parts in its own thread at
    once (it queued behind the other's part before)."""
    release, started = threading.Event(), threading.Event()

    def held():
        started.set()
        release.wait(30.0)
        return "held"

    other = threading.Thread(target=lambda: both(lambda: release.wait(30.0), held), daemon=True)
    other.start()
    try:
        assert started.wait(10.0)
        me = threading.current_thread().name
        here, there = _in_thread(lambda: both(lambda: threading.current_thread().name,
                                              lambda: threading.current_thread().name), timeout_s=5.0)
        assert here == there != me and not here.startswith("velab-fit-helper")
    finally:
        release.set()
        other.join(10.0)
    # free again: the second part goes to the helper
    here, there = both(lambda: threading.current_thread().name, lambda: threading.current_thread().name)
    assert there.startswith("velab-fit-helper") and here == threading.current_thread().name


def test_both_returns_both_results_and_raises_after_both_ended():
    done = threading.Event()

    def slow():
        done.wait(0.2)
        done.set()
        return 2

    def fails():
        raise ValueError("here")

    try:
        both(fails, slow)
    except ValueError:
        assert done.is_set()  # the helper's half had ended before the error came out
    else:
        raise AssertionError("both() swallowed the error")
    assert both(lambda: 1, lambda: 2) == (1, 2)


def test_map_each_keeps_the_items_order():
    assert map_each(lambda i: i * i, list(range(9))) == [i * i for i in range(9)]
    assert map_each(lambda i: i, []) == [] and map_each(lambda i: -i, [4]) == [-4]
