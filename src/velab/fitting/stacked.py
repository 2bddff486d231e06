"""Several runs' heads at one wall, stacked: the single fit's solvers on a joint fit (velab.fitting.joint)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from velab.fitting.engine import HeadEvaluator
from velab.fitting.parallel import both


@dataclass
class Count:
    """Evaluations of the stacked model (a Jacobian counts as one evaluation and one Jacobian): one per sweep,
    shared by the stacked evaluators it makes, each touched by one thread only (a fork counts on its own Count;
    velab.fitting.starts.fan_out adds it back after the threads joined)."""

    evaluations: int = 0
    jacobians: int = 0


class StackedEvaluator:
    """The heads of several runs at one wall, stacked: each run's rows weighted by w_r (its
    HeadEvaluator, on its own grid and flow). Quacks like a HeadEvaluator for velab.fitting.solvers
    and velab.fitting.summary (``head``, ``head_jac_x``, ``n_t``, counters, ``fork``). ``count``: where its
    evaluations are counted (a sweep's running total; its own if None)."""

    def __init__(self, evs: list[HeadEvaluator], weights, count: Count | None = None):
        self.evs = evs
        self.weights = np.asarray(weights, dtype=float)
        sizes = [e.n_t for e in evs]
        self.bounds = np.concatenate([[0], np.cumsum(sizes)])
        self.n_t = int(self.bounds[-1])
        self.count = count if count is not None else Count()

    @property
    def evaluations(self) -> int:
        return self.count.evaluations

    @evaluations.setter
    def evaluations(self, value: int) -> None:
        self.count.evaluations = value

    @property
    def jacobians(self) -> int:
        return self.count.jacobians

    @jacobians.setter
    def jacobians(self, value: int) -> None:
        self.count.jacobians = value

    def slices(self):
        return [slice(int(a), int(b)) for a, b in zip(self.bounds[:-1], self.bounds[1:])]

    def fork(self, workers: int | None = 1, **_) -> "StackedEvaluator":
        return StackedEvaluator([e.fork(workers=workers) for e in self.evs], self.weights)

    def stack(self, parts) -> np.ndarray:
        """Per-run vectors (on each run's grid) stacked and weighted as the rows."""
        return np.concatenate([w * np.asarray(p, dtype=float) for w, p in zip(self.weights, parts)])

    def _each(self, fill) -> None:
        """``fill(evaluator, weight, rows)`` for every run, the runs in two groups of about equal rows, one on
        the fit's helper thread (velab.fitting.parallel.both; each run's evaluation touches only its own buffers
        and its rows of the output, so the result does not depend on which thread ran it). A run's own grid is
        mostly too small for its evaluation to split in two (engine.SPLIT_MIN_BINS); the runs together are not
        (benchmarks/fit_joint.py: the joint fit's wall time 8 % lower, 5.07 s for 5.49)."""
        items = list(zip(self.evs, self.weights, self.slices()))
        if len(items) < 2:
            for item in items:
                fill(*item)
            return
        half = self.n_t / 2.0
        k = min(range(1, len(items)), key=lambda i: abs(self.bounds[i] - half))
        both(lambda: [fill(*item) for item in items[:k]], lambda: [fill(*item) for item in items[k:]])

    def head(self, a, J_rel, tau, out=None):
        self.count.evaluations += 1
        h = out if out is not None else np.empty(self.n_t)

        def fill(e, w, sl):
            h[sl] = e.head(a, J_rel, tau)
            h[sl] *= w

        self._each(fill)
        return h

    def head_jac_x(self, a, J_rel, tau, tau_free: bool = True, out=None):
        self.count.evaluations += 1
        self.count.jacobians += 1
        m = np.size(J_rel)
        rows = 2 + m + (m if tau_free else 0)
        if out is None:
            out = np.empty((rows, self.n_t))

        def fill(e, w, sl):
            h, jac = e.head_jac_x(a, J_rel, tau, tau_free)
            out[0, sl] = h
            out[1:, sl] = jac
            out[:, sl] *= w

        self._each(fill)
        return out[0], out[1:]
