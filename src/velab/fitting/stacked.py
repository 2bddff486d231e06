"""Several runs' heads at one wall, stacked: the single fit's solvers on a joint fit (velab.fitting.joint)."""

from __future__ import annotations

import numpy as np

from velab.fitting.engine import HeadEvaluator


class StackedEvaluator:
    """The heads of several runs at one wall, stacked: each run's rows weighted by w_r (its
    HeadEvaluator, on its own grid and flow). Quacks like a HeadEvaluator for velab.fitting.solvers
    and velab.fitting.summary (``head``, ``head_jac_x``, ``n_t``, counters, ``fork``)."""

    def __init__(self, evs: list[HeadEvaluator], weights):
        self.evs = evs
        self.weights = np.asarray(weights, dtype=float)
        sizes = [e.n_t for e in evs]
        self.bounds = np.concatenate([[0], np.cumsum(sizes)])
        self.n_t = int(self.bounds[-1])
        self.evaluations = 0
        self.jacobians = 0

    def slices(self):
        return [slice(int(a), int(b)) for a, b in zip(self.bounds[:-1], self.bounds[1:])]

    def fork(self, workers: int | None = 1, **_) -> "StackedEvaluator":
        return StackedEvaluator([e.fork(workers=workers) for e in self.evs], self.weights)

    def stack(self, parts) -> np.ndarray:
        """Per-run vectors (on each run's grid) stacked and weighted as the rows."""
        return np.concatenate([w * np.asarray(p, dtype=float) for w, p in zip(self.weights, parts)])

    def head(self, a, J_rel, tau, out=None):
        self.evaluations += 1
        h = self.stack([e.head(a, J_rel, tau) for e in self.evs])
        if out is not None:
            out[...] = h
            return out
        return h

    def head_jac_x(self, a, J_rel, tau, tau_free: bool = True, out=None):
        self.evaluations += 1
        self.jacobians += 1
        m = np.size(J_rel)
        rows = 2 + m + (m if tau_free else 0)
        if out is None:
            out = np.empty((rows, self.n_t))
        for e, w, sl in zip(self.evs, self.weights, self.slices()):
            h, jac = e.head_jac_x(a, J_rel, tau, tau_free)
            out[0, sl] = h
            out[1:, sl] = jac
            out[:, sl] *= w
        return out[0], out[1:]
