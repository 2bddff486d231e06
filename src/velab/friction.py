"""Friction laws of a pipe: steady Darcy friction factor and unsteady-friction weighting functions.

Pure functions of dimensionless numbers (Reynolds number, relative roughness,
dimensionless time / Laplace variable); the rig (``velab.rig.Rig``), the
frequency model (``velab.model.series_impedance``) and the method of
characteristics (``velab.moc``) all take their friction from here.

Steady friction
---------------
Darcy f from the Reynolds number of the *steady* flow Q0 (frozen: the standard
engineering choice; the transient does not change f). Laminar (Re < 2300):
f = 64/Re, whose head loss J = 32 nu Q / (g D^2 A) is linear in Q. Turbulent:
Blasius f = 0.316 Re^-1/4 (smooth pipe) or Colebrook-White
1/sqrt(f) = -2 log10(k/(3.7 D) + 2.51/(Re sqrt(f))) for a wall roughness k.

Unsteady friction (weighting functions)
---------------------------------------
The wall shear lags the mean flow. With tau = 4 nu t / D^2 (dimensionless time),
the extra friction slope is (Zielke 1968; Vardy & Brown 2003)

    J_u(t) = 16 nu / (g D^2 A) * integral_0^t W(tau(t - t')) dQ/dt'(t') dt'

* turbulent, smooth pipe (Vardy & Brown 2003):
  W(tau) = A* exp(-B* tau) / sqrt(tau), A* = 1/(2 sqrt(pi)), B* = Re^kappa / 12.86,
  kappa = log10(15.29 / Re^0.0567); Laplace transform W^(p) = 1 / (2 sqrt(p + B*));
* laminar (Zielke 1968): W(tau) = sum_k exp(-j_(2,k)^2 tau), j_(2,k) the zeros of
  the Bessel function J2; W^(p) = sum_k 1/(p + j_(2,k)^2) = (I0(x)/I2(x) - 1)/4 - 2/p,
  x = sqrt(p) (the exact laminar series impedance minus inertia and Poiseuille).

B* and the laminar/turbulent choice use the steady Reynolds number (frozen, as f).
J_u is linear in Q, so in the frequency domain it is exactly the resistance
R_u(s) = 4 s/(g A) W^(s D^2 / (4 nu)) per unit length (:func:`unsteady_resistance`).
In the time domain the convolution is a sum of exponentials, each updated
recursively (Trikha 1975; Vitkovsky et al. 2004): :func:`weighting_exponentials`.
"""

from __future__ import annotations

import math

import numpy as np

LAMINAR_RE = 2300.0

STEADY_LAWS = ("quadratic", "linear", "none")
FACTOR_LAWS = ("blasius", "colebrook")
UNSTEADY_LAWS = ("none", "vardy-brown", "brunone")

_ZIELKE_EXACT_TERMS = 24  # leading exponentials of Zielke's W kept exactly; the rest by quadrature


# --------------------------------------------------------------------------- steady


def darcy_factor(reynolds: float, law: str = "blasius", relative_roughness: float = 0.0) -> float:
    """Darcy friction factor f at Reynolds number Re (0 for Re = 0)."""
    re = abs(float(reynolds))
    if re == 0.0:
        return 0.0
    if re < LAMINAR_RE:
        return 64.0 / re
    if law == "blasius":
        return 0.316 * re**-0.25
    if law == "colebrook":
        return colebrook(re, relative_roughness)
    raise ValueError(f"friction factor law must be one of {FACTOR_LAWS}, got {law!r}")


def colebrook(reynolds: float, relative_roughness: float) -> float:
    """Colebrook-White f for Re and k/D, solved to rounding (Newton on x = 1/sqrt(f))."""
    re, r = float(reynolds), float(relative_roughness)
    # Swamee-Jain start, within a few % everywhere in the turbulent range
    x = -2.0 * math.log10(r / 3.7 + 5.74 / re**0.9)
    c = 2.0 / math.log(10.0)
    for _ in range(50):
        arg = r / 3.7 + 2.51 * x / re
        g = x + 2.0 * math.log10(arg)
        dg = 1.0 + c * (2.51 / re) / arg
        step = g / dg
        x -= step
        if abs(step) < 1e-15 * abs(x):
            break
    return 1.0 / (x * x)


# --------------------------------------------------------------------------- unsteady


def vardy_brown_decay(reynolds: float) -> float:
    """Vardy-Brown B* = Re^kappa / 12.86, kappa = log10(15.29 / Re^0.0567) (smooth turbulent pipes)."""
    re = abs(float(reynolds))
    kappa = math.log10(15.29 / re**0.0567)
    return re**kappa / 12.86


def weighting_laplace(p, reynolds: float) -> np.ndarray:
    """Laplace transform W^(p) of the weighting function in dimensionless time (p = s D^2 / (4 nu)).

    Vardy-Brown 1 / (2 sqrt(p + B*)) for turbulent flow, Zielke's exact laminar
    transform otherwise. W^(0) is finite (1/12 laminar), so the steady friction is unchanged.
    """
    p = np.asarray(p, dtype=complex)
    if abs(reynolds) >= LAMINAR_RE:
        return 0.5 / np.sqrt(p + vardy_brown_decay(reynolds))
    out = np.full(p.shape, 1.0 / 12.0, dtype=complex)  # the p -> 0 limit, sum_k 1/j_(2,k)^2
    big = np.abs(p) > 1e-4
    x = np.sqrt(p[big])
    # I0/I2 with exponentially scaled Bessel functions (no overflow for large |x|)
    from scipy import special  # (0.3 s of import: only when the unsteady friction is evaluated)

    ratio = special.ive(0, x) / special.ive(2, x)
    out[big] = 0.25 * (ratio - 1.0) - 2.0 / p[big]
    small = ~big
    out[small] = 1.0 / 12.0 - p[small] * _ZIELKE_SUM_INV4
    return out


# sum_k 1/j_(2,k)^4 = 1/(16 (nu+1)^2 (nu+2)) for nu = 2: the slope of W^ at p = 0
_ZIELKE_SUM_INV4 = 1.0 / (16.0 * 9.0 * 4.0)


def unsteady_resistance(s, *, gravity_area: float, diameter_m: float, kinematic_viscosity_m2_s: float,
                        reynolds: float) -> np.ndarray:
    """R_u(s) = 4 s / (g A) W^(s D^2 / (4 nu)): the weighting-function friction per unit length (s/m^3 per m)."""
    s = np.asarray(s, dtype=complex)
    p = s * diameter_m**2 / (4.0 * kinematic_viscosity_m2_s)
    return 4.0 * s / gravity_area * weighting_laplace(p, reynolds)


def weighting_exponentials(reynolds: float, step: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Weights m_k and rates n_k with W(tau) ~= sum_k m_k exp(-n_k tau) for all tau > 0.

    1/sqrt(tau) = (2/sqrt(pi)) integral_0^inf exp(-u^2 tau) du, so Vardy-Brown's
    W = (1/pi) integral_0^inf exp(-(B* + u^2) tau) du is a continuous sum of
    exponentials; the trapezoidal rule in y = ln u (spacing ``step``) makes it a finite
    one whose Laplace transform matches 1/(2 sqrt(p + B*)) to about
    exp(-pi^2 / (2 step)) relative on and right of the imaginary axis (see the tests).
    Zielke's W keeps its first terms exactly; the rest, sum_k exp(-j_(2,k)^2 tau) with
    zeros about pi apart, is (1/pi) integral_(u0)^inf exp(-u^2 tau) du, done the same way
    with u = u0 + e^y. The nodes run up to rates of 1e16, far beyond any time step:
    the caller folds the terms that decay within one step into an instantaneous weight.
    """
    re = abs(float(reynolds))
    if re >= LAMINAR_RE:
        b = vardy_brown_decay(re)
        u0, scale = 0.0, math.sqrt(b)
        m_exact, n_exact = np.zeros(0), np.zeros(0)
    else:
        from scipy import special  # (0.3 s of import: only when Zielke's weighting function is built)

        zeros = special.jn_zeros(2, _ZIELKE_EXACT_TERMS)
        b = 0.0
        u0 = scale = zeros[-1] + math.pi / 2  # midpoint between the last kept zero and the next
        m_exact, n_exact = np.ones(zeros.size), zeros**2
    y = np.arange(math.log(1e-8 * scale), math.log(1e8), step)
    e = np.exp(y)
    m = step * e / math.pi
    n = b + (u0 + e) ** 2
    # nodes far below the scale all have the rate b + u0^2 to 1e-4: one term carries them
    low = e < 1e-2 * scale
    n_low = b + (u0 + np.average(e[low], weights=m[low])) ** 2
    return np.concatenate([m_exact, [m[low].sum()], m[~low]]), np.concatenate([n_exact, [n_low], n[~low]])
