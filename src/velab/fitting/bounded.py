"""A bounded scalar minimiser: scipy.optimize's ``minimize_scalar(method="bounded")``, step for step.

The one scipy.optimize call of a default fit is the equivalent friction's bounded search on one variable
(velab.fitting.friction.equivalent_friction, 12 calls of ~10 evaluations on the default record); importing
scipy.optimize for it cost ~0.2-0.4 s of every ``velab fit`` process's start-up (scipy.optimize imports
scipy.sparse, scipy.spatial and scipy.constants too). This is scipy 1.17's
``scipy.optimize._optimize._minimize_scalar_bounded`` (BSD-3-Clause, Copyright (c) 2001-2002 Enthought, Inc.
and 2003-2024 SciPy Developers), transcribed without its printing: Brent's method (golden-section steps and
parabolic interpolation, absolute tolerance ``xatol`` on x), its arithmetic in its order, so the points it
evaluates and the minimum it returns are scipy's to the last bit (tests/fitting/test_bounded.py compares the
two on many functions; a later scipy that changed its algorithm would show there). The solvers
that only non-default options need (Nelder-Mead, differential evolution) still come from scipy.optimize,
imported when they are used.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable


@dataclass(frozen=True)
class BoundedMin:
    x: float  # the best point evaluated
    fun: float  # its value
    nfev: int  # evaluations
    status: int  # 0 converged, 1 maxiter evaluations reached, 2 NaN met (scipy's codes)


def _sign(v: float) -> float:
    """numpy's sign: -1, 0 or 1, NaN for NaN."""
    if v > 0.0:
        return 1.0
    if v < 0.0:
        return -1.0
    return v if v != v else 0.0


def _maximum(a: float, b: float) -> float:
    """numpy's maximum of two floats: NaN if either is NaN."""
    if a != a or b != b:
        return math.nan
    return a if a >= b else b


def minimize_bounded(func: Callable[[float], float], bounds: tuple[float, float], *, xatol: float = 1e-5,
                     maxiter: int = 500) -> BoundedMin:
    """The minimum of ``func`` on ``bounds`` = (lo, hi): scipy.optimize.minimize_scalar(func, bounds=bounds,
    method="bounded", options={"xatol": xatol, "maxiter": maxiter}), the same evaluations and result."""
    if len(bounds) != 2:
        raise ValueError("bounds must have two elements.")
    x1, x2 = bounds
    if not (math.isfinite(x1) and math.isfinite(x2)):
        raise ValueError("Optimization bounds must be finite scalars.")
    if x1 > x2:
        raise ValueError("The lower bound exceeds the upper bound.")
    maxfun = maxiter
    flag = 0
    sqrt_eps = math.sqrt(2.2e-16)
    golden_mean = 0.5 * (3.0 - math.sqrt(5.0))
    a, b = x1, x2
    fulc = a + golden_mean * (b - a)
    nfc, xf = fulc, fulc
    rat = e = 0.0
    x = xf
    fx = func(x)
    num = 1
    fu = math.inf

    ffulc = fnfc = fx
    xm = 0.5 * (a + b)
    tol1 = sqrt_eps * abs(xf) + xatol / 3.0
    tol2 = 2.0 * tol1

    while abs(xf - xm) > (tol2 - 0.5 * (b - a)):
        golden = 1
        # a parabolic step?
        if abs(e) > tol1:
            golden = 0
            r = (xf - nfc) * (fx - ffulc)
            q = (xf - fulc) * (fx - fnfc)
            p = (xf - fulc) * q - (xf - nfc) * r
            q = 2.0 * (q - r)
            if q > 0.0:
                p = -p
            q = abs(q)
            r = e
            e = rat
            # is the parabola acceptable?
            if (abs(p) < abs(0.5 * q * r)) and (p > q * (a - xf)) and (p < q * (b - xf)):
                rat = (p + 0.0) / q
                x = xf + rat
                if ((x - a) < tol2) or ((b - x) < tol2):
                    si = _sign(xm - xf) + ((xm - xf) == 0)
                    rat = tol1 * si
            else:  # a golden-section step
                golden = 1

        if golden:  # a golden-section step
            if xf >= xm:
                e = a - xf
            else:
                e = b - xf
            rat = golden_mean * e

        si = _sign(rat) + (rat == 0)
        x = xf + si * _maximum(abs(rat), tol1)
        fu = func(x)
        num += 1

        if fu <= fx:
            if x >= xf:
                a = xf
            else:
                b = xf
            fulc, ffulc = nfc, fnfc
            nfc, fnfc = xf, fx
            xf, fx = x, fu
        else:
            if x < xf:
                a = x
            else:
                b = x
            if (fu <= fnfc) or (nfc == xf):
                fulc, ffulc = nfc, fnfc
                nfc, fnfc = x, fu
            elif (fu <= ffulc) or (fulc == xf) or (fulc == nfc):
                fulc, ffulc = x, fu

        xm = 0.5 * (a + b)
        tol1 = sqrt_eps * abs(xf) + xatol / 3.0
        tol2 = 2.0 * tol1

        if num >= maxfun:
            flag = 1
            break

    if math.isnan(xf) or math.isnan(fx) or math.isnan(fu):
        flag = 2
    return BoundedMin(float(xf), float(fx), num, flag)
