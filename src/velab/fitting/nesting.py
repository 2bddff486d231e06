"""Nesting of the calibrated models, backwards: a larger model hands a better optimum back.

Forwards, every S(m) is started from S(m-1) and guarded by it (velab.fitting.sweep), so
F(S(m)) <= F(S(m-1)). The multi-start search of S(m-1) can still miss an optimum that
S(m) then finds with one element vanished or split in two (two elements at one retardation
time): S(m) is then S(m-1)-shaped but fits better than S(m-1), and the table would reward
S(m) for a parameter it does not use. After the forward pass, each S(m-1) is therefore also
started from S(m) with one element dropped and with its two closest elements merged
(velab.fitting.starts.reduce_starts), when that start already fits better than S(m-1);
the forward guard then runs again over the family.
"""

from __future__ import annotations

import math

import numpy as np

from velab.fitting.starts import reduce_starts

# a start handed back must fit better than the smaller model by more than this in n ln F: below it,
# the difference is rounding (an S(m) that is S(m-1) plus a vanished element hands S(m-1) back
# 1e-15 relative "better", and polishing and refreshing that cost a second on a low-noise record)
MIN_GAIN = 1e-6
# S(m) = S(m-1) plus a vanished element is not tried (its reduced starts are S(m-1) itself and what
# S(m-1) hands to S(m-2)); a switch for benchmarks/fit_sweep.py's "previous sweep"
SKIP_EMBEDDED = True


def hand_back(sw, family: list[tuple[int, bool]], spent: dict) -> None:
    """Backward pass over ``family`` (jobs (m, reduced) in increasing m, each containing the
    previous one) on the sweep ``sw``; ``spent[job]`` accumulates [evaluations, jacobians, starts]."""
    jobs = [j for j in family if j in sw.final]
    if len(jobs) < 2:
        return
    changed = False
    for small_job, big_job in reversed(list(zip(jobs[:-1], jobs[1:]))):
        small, big = sw.final[small_job], sw.final[big_job]
        pm = small.sol.pm
        if big.sol.pm.m != pm.m + 1 or SKIP_EMBEDDED and np.array_equal(big.sol.x, big.sol.pm.embed(pm, small.sol.x)):
            continue  # (S(m) = S(m-1) plus a vanished element has nothing S(m-1) lacks to hand back)
        big = sw.current(big)  # its correction under the current friction (a full-band evaluation)
        before = sw.counts()
        stage = sw.final_stage(big.corr)
        starts = sorted(((stage.F(pm, x0), i, x0) for i, x0 in enumerate(reduce_starts(big.sol, pm))),
                        key=lambda c: c[:2])
        for F0, _, x0 in starts[:2]:
            if not F0 < small.sol.F * math.exp(-MIN_GAIN / sw.d.size):  # n ln(F_small / F0) > MIN_GAIN
                break
            cand = sw.refresh(pm, sw.polish_final(stage, pm, x0), big.corr)
            if cand.sol.F < small.sol.F:
                small = cand
                sw.final[small_job] = cand
                changed = True
        after = sw.counts()
        spent[small_job][0] += after[0] - before[0]
        spent[small_job][1] += after[1] - before[1]
    if not changed:
        return
    for small_job, big_job in zip(jobs[:-1], jobs[1:]):
        small, big = sw.current(sw.final[small_job]), sw.final[big_job]
        if big.sol.F > small.sol.F:
            before = sw.counts()
            sw.final[big_job] = sw.guard(big.sol.pm, small, sw.current(big))
            after = sw.counts()
            spent[big_job][0] += after[0] - before[0]
            spent[big_job][1] += after[1] - before[1]
