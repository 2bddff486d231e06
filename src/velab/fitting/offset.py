"""The steady head fitted with every model, the baseline its prior (a linear nuisance projected out).

The fit's data are the head minus the baseline's mean (velab.fitting.window.steady_head), whose error,
sigma / sqrt(n_b) (0.27 mm at 12 mm of noise and 2000 samples), is the same for every model but is not
made up for alike: creep elements can only take up a steady head set too high, by a slow element on
the upper bound of tau (a ramp) or by a slowest element split in two. On the simulated bench (material A,
S3 true) a baseline mean 2.3 standard errors high put S3 18 AIC units behind S5, 1.6 high 10 behind;
as low, nothing. Here every model's head is H0 + delta + h(t), with delta fitted:

    S(x) = min over delta of  sum_window (r_i(x) + delta)^2 + n_b delta^2,    r = h(x) - d,

so the baseline's n_b samples weigh as n_b observations of the steady head and the window adds what the
model says of it. delta is linear and solved in closed form, delta = -sum(r) / (n + n_b), and
S = |r|^2 - (sum r)^2 / (n + n_b). The map r -> [r + delta, sqrt(n_b) delta] is linear (Golub & Pereyra's
projection of a linear parameter): residuals and Jacobian columns go through it alike, and the Gram
matrix of [r; J] loses the rank-one s s^T / (n + n_b), s its rows' sums. Every model carries the same
extra parameter, so AIC differences do not depend on counting it; k does not count it.

``n_b = 0`` (no baseline: a record imported without samples before the trigger, a joint fit's stacked
runs) is the previous objective exactly: the steady head as the baseline gave it.
"""

from __future__ import annotations

import math

import numpy as np

from velab.fitting.engine import sumsq


def offset(r: np.ndarray, n_b: float) -> float:
    """delta of the residuals ``r`` (model minus data, on the window): what the model adds to the
    baseline's steady head (m); 0 without a baseline."""
    if not n_b > 0:
        return 0.0
    return -float(np.sum(r)) / (r.size + n_b)


def objective(r: np.ndarray, n_b: float) -> float:
    """S: the residuals' sum of squares with the offset fitted (the baseline's term included)."""
    ss = sumsq(r)
    if not n_b > 0:
        return ss
    s = float(np.sum(r))
    return max(ss - s * s / (r.size + n_b), 0.0)


def fitted(r: np.ndarray, n_b: float) -> np.ndarray:
    """The window's residuals with the offset fitted (r + delta)."""
    return r if not n_b > 0 else r + offset(r, n_b)


def augment(v: np.ndarray, n_b: float) -> np.ndarray:
    """The linear map r -> [r + delta(r), sqrt(n_b) delta(r)] on the last axis (residuals or Jacobian
    rows): |augment(r)|^2 = objective(r), and augment(J) is the projected Jacobian. No baseline: ``v``."""
    if not n_b > 0:
        return v
    v = np.asarray(v, dtype=float)
    d = -v.sum(axis=-1, keepdims=True) / (v.shape[-1] + n_b)
    return np.concatenate([v + d, math.sqrt(n_b) * d], axis=-1)


def project_gram(M: np.ndarray, rows: np.ndarray, n_b: float) -> np.ndarray:
    """The Gram matrix ``M`` of ``rows`` ([r; J], length n each) as that of their augmented rows."""
    if not n_b > 0:
        return M
    s = rows.sum(axis=1)
    return M - np.outer(s, s) / (rows.shape[1] + n_b)
