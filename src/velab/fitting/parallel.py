"""Two-way parallel work for the fitter: one shared helper thread.

A full-band evaluation (velab.fitting.engine) is a few large numpy passes over the frequency
bins and a batched inverse FFT, all of which release the GIL: split in two halves (bins, then
rows), the second half on the helper thread, it runs about 1.8 x faster on two free cores, with
bit-identical results (every operation is per bin or per row). One helper per process, started
on first use (and again in a forked child). The helper takes a part only when it is free: a
:func:`both` that finds it busy (another fit thread's part, or work handed to the helper that splits
again) runs its two parts in the calling thread, one after the other. So nothing waits in a queue
behind another's work and nothing deadlocks, and results never depend on which thread ran what.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, TypeVar

T = TypeVar("T")
U = TypeVar("U")

_helper: ThreadPoolExecutor | None = None
_lock = threading.Lock()
_busy = threading.Lock()  # held while the helper has a part to run (taken without waiting)


def _forget_helper() -> None:
    """In a forked child the helper thread does not exist (only its executor object was copied):
    start afresh on first use, with new locks (the parent's may have been held at the fork)."""
    global _helper, _lock, _busy
    _helper = None
    _lock = threading.Lock()
    _busy = threading.Lock()


os.register_at_fork(after_in_child=_forget_helper)


def _pool() -> ThreadPoolExecutor:
    global _helper
    with _lock:
        if _helper is None:
            _helper = ThreadPoolExecutor(max_workers=1, thread_name_prefix="velab-fit-helper")
        return _helper


def both(here: Callable[[], T], there: Callable[[], U]) -> tuple[T, U]:
    """Run ``there`` on the helper thread and ``here`` in the calling thread; both results.
    An exception in either is raised here (after both have ended: no half is left running).
    With the helper busy (or on the helper itself), both run here, one after the other."""
    if not _busy.acquire(blocking=False):
        return here(), there()
    try:
        fut = _pool().submit(there)
        try:
            a = here()
        finally:
            b = fut.result()  # waits even if ``here`` raised: the buffers are shared
    finally:
        _busy.release()
    return a, b


def map_pair(fn: Callable[[object, T], U], items: list[T], make_context: Callable[[], object],
             parallel: bool = True) -> list[U]:
    """[fn(context, item) for item in items], the items shared out between the calling thread and
    the helper, each with its own ``make_context()`` (e.g. an evaluator fork). The results are in
    the items' order and do not depend on which thread ran which item, as long as ``fn``'s result
    depends only on the item (the context holds work buffers, not state). A :func:`both` inside
    ``fn`` finds the helper busy and runs its parts in turn. With the helper busy when called, the
    items run here, in turn."""
    if not parallel or len(items) < 2:
        ctx = make_context()
        return [fn(ctx, it) for it in items]
    out: list = [None] * len(items)
    nxt = iter(range(len(items)))
    lock = threading.Lock()

    def worker(ctx) -> None:
        while True:
            with lock:
                i = next(nxt, None)
            if i is None:
                return
            out[i] = fn(ctx, items[i])

    c0, c1 = make_context(), make_context()
    both(lambda: worker(c0), lambda: worker(c1))
    return out


def map_each(fn: Callable[[T], U], items: list[T]) -> list[U]:
    """[fn(item) for item in items] shared out between the calling thread and the helper on a machine
    with two cores or more (:func:`map_pair` with no context): for work that touches only its own
    item's objects, so the results do not depend on which thread ran which."""
    return map_pair(lambda _, item: fn(item), items, lambda: None, parallel=(os.cpu_count() or 1) > 1)
