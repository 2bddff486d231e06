"""velab.fitting.parallel: the fitter's one helper thread."""

import threading

from velab.fitting.parallel import both, map_pair


def test_work_on_the_helper_that_splits_again_runs_there_in_turn():
    """A fit handed to the helper (a joint fit's per-run work) whose own work splits in two (a time-domain
    polish's Jacobian columns): on the helper the two parts run one after the other. The helper waited for
    itself before: that call never returned."""
    names = []

    def inner(i):
        a, b = both(lambda: (i, threading.current_thread().name), lambda: (-i, threading.current_thread().name))
        names.append((a[1], b[1]))
        return a[0] + b[0] + 10 * i

    out = {}

    def run():
        out["result"] = map_pair(lambda _, i: inner(i), list(range(6)), lambda: None)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(30.0)
    assert not t.is_alive(), "map_pair over work that calls both() did not return"
    assert out["result"] == [10 * i for i in range(6)]
    # on the helper, both parts ran on the helper; elsewhere the second part went to the helper
    helper = [n for n in names if n[0].startswith("velab-fit-helper")]
    assert helper and all(a == b for a, b in helper)
    assert all(b.startswith("velab-fit-helper") for _, b in names)


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
