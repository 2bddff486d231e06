"""velab.fitting.bounded: scipy.optimize.minimize_scalar(method="bounded") step for step, without scipy.optimize's
import (the equivalent friction's search on every default fit). The points evaluated, the minimum, its value and
the evaluation count are scipy's to the last bit; scipy is imported here only, as the reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from velab.fitting.bounded import minimize_bounded


def _recorded(f):
    seen = []

    def g(x):
        seen.append(float(x))
        return f(x)

    return g, seen


rng = np.random.default_rng(7)
_c = rng.normal(size=(6, 4))
FUNCTIONS = {
    "quadratic inside": lambda x: (x - 0.3) ** 2 + 1.0,
    "quadratic at the lower bound": lambda x: (x + 3.0) ** 2,
    "quadratic at the upper bound": lambda x: (x - 7.0) ** 2,
    "abs (a kink)": lambda x: abs(x - 0.1234567),
    "quartic flat bottom": lambda x: (x - 0.2) ** 4,
    "cosine, several minima": lambda x: math.cos(5.0 * x) + 0.1 * x,
    "constant": lambda x: 2.5,
    "step": lambda x: 0.0 if x < 0.37 else 1.0,
    "exp": lambda x: math.exp(x) - 2.0 * x,
    "rational": lambda x: 1.0 / (1.0 + (x - 0.6) ** 2) * -1.0,
    "NaN beyond 0.5": lambda x: math.nan if x > 0.5 else (x - 0.9) ** 2,
    **{f"random polynomial {i}": (lambda c: lambda x: float(np.polyval(c, x)) + x * x)(_c[i]) for i in range(6)},
}
BOUNDS = [(-1.0, 1.0), (0.0, 10.0), (-5.0, -4.0), (-1e-3, 2e-3), (0.25, 0.25), (-100.0, 100.0)]


@pytest.mark.parametrize("name", sorted(FUNCTIONS))
def test_the_same_evaluations_and_minimum_as_scipy(name):
    f = FUNCTIONS[name]
    for lo, hi in BOUNDS:
        for xatol, maxiter in ((1e-3, 500), (1e-5, 500), (1e-10, 500), (1e-5, 4)):
            g1, seen1 = _recorded(f)
            g2, seen2 = _recorded(f)
            ref = minimize_scalar(g1, bounds=(lo, hi), method="bounded", options={"xatol": xatol, "maxiter": maxiter})
            got = minimize_bounded(g2, (lo, hi), xatol=xatol, maxiter=maxiter)
            where = f"{name} on [{lo}, {hi}], xatol {xatol}, maxiter {maxiter}"
            assert seen2 == seen1 or np.array_equal(seen2, seen1, equal_nan=True), where
            assert np.array_equal([got.x, got.fun], [float(ref.x), float(ref.fun)], equal_nan=True), where
            assert (got.nfev, got.status) == (ref.nfev, ref.status), where


def test_the_equivalent_friction_search_is_scipys():
    """The fit's own call (velab.fitting.friction.equivalent_friction's cost on (-1, 1), xatol 1e-3) on a
    cost of its shape: a smooth bowl in the resistance's share."""
    for centre in (-0.7, -0.2, 0.0, 0.31, 0.95):
        cost = lambda v, c=centre: 0.8 + (v - c) ** 2 * (1.0 + 0.3 * v)  # noqa: E731
        ref = minimize_scalar(cost, bounds=(-1.0, 1.0), method="bounded", options={"xatol": 1e-3})
        got = minimize_bounded(cost, (-1.0, 1.0), xatol=1e-3)
        assert (got.x, got.fun, got.nfev) == (float(ref.x), float(ref.fun), ref.nfev)


@pytest.mark.parametrize("bounds", [(1.0, 0.0), (0.0, math.inf), (math.nan, 1.0)])
def test_bad_bounds_are_refused_as_scipy_refuses_them(bounds):
    with pytest.raises(ValueError):
        minimize_scalar(lambda x: x * x, bounds=bounds, method="bounded")
    with pytest.raises(ValueError):
        minimize_bounded(lambda x: x * x, bounds)
