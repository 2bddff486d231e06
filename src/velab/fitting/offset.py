"""The steady head fitted with every model, the baseline its prior (a linear nuisance projected out).

The fit's data are the head minus the baseline's mean (velab.fitting.window.steady_head), whose error,
sigma / sqrt(n_b) (0.27 mm at 12 mm of noise and 2000 samples), is the same for every model but is not
made up for alike: creep elements can only take up a steady head set too high (docs/decisions.md). Here
every model's head is H0 + delta + h(t), with delta fitted:

    S(x) = min over delta of  sum_window (r_i(x) + delta)^2 + n_b delta^2,    r = h(x) - d,

so the baseline's n_b samples weigh as n_b observations of the steady head and the window adds what the
model says of it. delta is linear and solved in closed form, delta = -sum(r) / (n + n_b), and
S = |r|^2 - (sum r)^2 / (n + n_b) = r^T P r, P = I - 1 1^T / (n + n_b) (Golub & Pereyra's projection of a
linear parameter). P = Q^T Q with Q = I - c 1 1^T, c = (1 - sqrt(n_b / (n + n_b))) / n: residuals and
Jacobian columns go through Q alike and keep their length (slices of a stacked fit stay valid), and the
Gram matrix of [r; J] loses the rank-one s s^T / (n + n_b), s its rows' sums. Every model carries the
same extra parameter, so AIC differences do not depend on counting it; k does not count it.

The baseline ``b`` is n_b (one record: the whole vector) or, for a stacked fit (velab.fitting.joint: runs,
sections), a tuple of blocks (start, stop, n_b), each part its own offset and baseline. The formulas are
the same on a block whose rows are weighted (w r, w J). n_b = 0 (no baseline: a record imported without
samples before the trigger) is the previous objective exactly: the steady head as the data have it.
"""

from __future__ import annotations

import math

import numpy as np

from velab.fitting.engine import sumsq


def _blocks(size: int, b) -> list[tuple[int, int, float]]:
    """The baseline ``b`` as blocks (start, stop, n_b) with n_b > 0."""
    if isinstance(b, (tuple, list)):
        return [(int(i), int(j), float(n)) for i, j, n in b if n > 0 and j > i]
    return [(0, size, float(b))] if b and b > 0 else []


def counted_on(n_b: float, n: int, size: int) -> float:
    """A baseline of ``n_b`` samples at the fit rate, counted on a grid that holds ``size`` of the window's
    ``n`` samples (a decimated stage): its prior weighs the same against the window there."""
    return n_b * size / n


def offset(r: np.ndarray, n_b: float) -> float:
    """delta of the residuals ``r`` (model minus data, one record's window): what the model adds to the
    baseline's steady head (m); 0 without a baseline."""
    if not n_b > 0:
        return 0.0
    return -float(np.sum(r)) / (r.size + n_b)


def objective(r: np.ndarray, b) -> float:
    """S: the residuals' sum of squares with the offsets fitted (the baselines' terms included)."""
    ss = sumsq(r)
    for i, j, n_b in _blocks(r.size, b):
        s = float(np.sum(r[i:j]))
        ss -= s * s / (j - i + n_b)
    return max(ss, 0.0)


def fitted(r: np.ndarray, b) -> np.ndarray:
    """The residuals with the offsets fitted (r + delta on each block)."""
    blocks = _blocks(r.size, b)
    if not blocks:
        return r
    out = np.array(r, dtype=float)
    for i, j, n_b in blocks:
        out[i:j] += offset(out[i:j], n_b)
    return out


def project(v: np.ndarray, b) -> np.ndarray:
    """Q v on the last axis (residuals or Jacobian rows), block by block: |Q r|^2 = objective(r), and Q J is
    the Jacobian with the offsets projected out. Without a baseline: ``v``."""
    blocks = _blocks(np.shape(v)[-1], b)
    if not blocks:
        return v
    out = np.array(v, dtype=float)
    for i, j, n_b in blocks:
        n = j - i
        c = (1.0 - math.sqrt(n_b / (n + n_b))) / n
        out[..., i:j] -= c * out[..., i:j].sum(axis=-1, keepdims=True)
    return out


def project_gram(M: np.ndarray, rows: np.ndarray, b) -> np.ndarray:
    """The Gram matrix ``M`` of ``rows`` ([r; J]) as that of their projected rows."""
    blocks = _blocks(rows.shape[1], b)
    if not blocks:
        return M
    M = M.copy()
    for i, j, n_b in blocks:
        s = rows[:, i:j].sum(axis=1)
        M -= np.outer(s, s) / (j - i + n_b)
    return M

