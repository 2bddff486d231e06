"""Column separation (physics.md section 11): the vapour-pressure head, the predicted downsurge, detection.

When the downsurge after the closure brings the absolute pressure at the valve down to the
vapour pressure of the water, a vapour cavity forms there, the head sits at the vapour-pressure
head and the cavity's collapse sends spikes above the Joukowsky head. No model of velab (the
frequency-domain model, the MOC) holds there. So:

* the interlock refuses, before anything moves, a manoeuvre whose predicted first downsurge
  (steady head - Joukowsky head of the flow stopped, with the interlock's surge margin) reaches
  the vapour-pressure head (``predict_downsurge``; velab.recording.safety, ``velab synth``);
* a record whose head comes within ``DETECTION_MARGIN_M`` of it is flagged (``cavitating``) and
  the fit warns that its model does not hold there (velab.fitting.adequacy).

Heads are gauge heads at the transducer (as everywhere in velab): the vapour-pressure head is
(p_v(T) - p_atm) / (rho g), about -10.1 m for water at 20 C at sea level.

Pure functions, no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

GRAVITY_M_S2 = 9.81  # velab.rig's
P_ATM_PA = 101_325.0  # standard atmosphere (a lab well above sea level has less: pass it)
DEFAULT_TEMPERATURE_C = 20.0
# a record sample within this of the vapour-pressure head counts as cavitating: the transducer's
# accuracy (0.15 % of 6 bar is 0.9 kPa, 0.09 m) and its noise are well inside, a real cavity's
# plateau (the head pinned at p_v for tens of ms) is not missed
DETECTION_MARGIN_M = 0.5

# IAPWS-IF97 region 4, the saturation-pressure equation (Wagner et al. 2000, eq. 30)
_N = (0.11670521452767e4, -0.72421316703206e6, -0.17073846940092e2, 0.12020824702470e5,
      -0.32325550322333e7, 0.14915108613530e2, -0.48232657361591e4, 0.40511340542057e6,
      -0.23855557567849, 0.65017534844798e3)
T_MIN_C, T_MAX_C = 0.0, 100.0  # liquid water at atmospheric pressure (the rig file's range)


def vapour_pressure_pa(temperature_c: float = DEFAULT_TEMPERATURE_C) -> float:
    """Saturation pressure of water (Pa) at ``temperature_c`` (IAPWS-IF97: 2339.2 Pa at 20 C)."""
    t = float(temperature_c)
    if not (T_MIN_C <= t <= 373.946):  # the equation holds from 273.15 K to the critical point
        raise ValueError(f"water temperature {t:g} C is outside 0..374 C")
    n1, n2, n3, n4, n5, n6, n7, n8, n9, n10 = _N
    T = t + 273.15
    th = T + n9 / (T - n10)
    A = th * th + n1 * th + n2
    B = n3 * th * th + n4 * th + n5
    C = n6 * th * th + n7 * th + n8
    p_mpa = (2 * C / (-B + math.sqrt(B * B - 4 * A * C))) ** 4
    return p_mpa * 1e6


def vapour_head_m(temperature_c: float = DEFAULT_TEMPERATURE_C, density_kg_m3: float = 998.2,
                  p_atm_pa: float = P_ATM_PA) -> float:
    """Gauge vapour-pressure head (p_v - p_atm) / (rho g), m (negative: -10.1 m at 20 C)."""
    return (vapour_pressure_pa(temperature_c) - p_atm_pa) / (density_kg_m3 * GRAVITY_M_S2)


def rig_temperature_c(rig) -> float:
    """The rig's water temperature (``[fluid] temperature_c``; 20 C for rigs stored without it)."""
    return float(getattr(rig.fluid, "temperature_c", DEFAULT_TEMPERATURE_C))


def rig_vapour_head_m(rig, p_atm_pa: float = P_ATM_PA) -> float:
    """The vapour-pressure head of the rig's water at its temperature and density."""
    return vapour_head_m(rig_temperature_c(rig), rig.fluid.density_kg_m3, p_atm_pa)


@dataclass(frozen=True)
class DownsurgePrediction:
    steady_head_m: float
    steady_flow_m3_s: float
    downsurge_m: float  # Joukowsky head of the flow stopped, with the margin
    min_head_m: float  # steady head - downsurge
    vapour_head_m: float
    temperature_c: float
    allowed: bool
    message: str  # one line; names cavitation and the vapour-pressure head when refused


def predict_downsurge(rig, steady_head_m: float | None = None, steady_flow_m3_s: float | None = None, *,
                      surge_margin: float = 0.1, closed_fraction: float = 1.0,
                      p_atm_pa: float = P_ATM_PA) -> DownsurgePrediction:
    """The first downsurge after the closure: the head falls about the Joukowsky head a dQ/(gA) below the
    steady head (less the damping, which the prediction leaves out: conservative), plus ``surge_margin``
    of it. ``closed_fraction``: the share of the flow the manoeuvre stops (1 for a full closure).
    Refused (``allowed`` False) when the minimum reaches the vapour-pressure head."""
    h0 = rig.steady_head_m if steady_head_m is None else float(steady_head_m)
    q0 = rig.steady_flow_m3_s if steady_flow_m3_s is None else float(steady_flow_m3_s)
    a = rig.nominal_wave_speed_m_s
    jouk = a * q0 / (GRAVITY_M_S2 * rig.pipe.area_m2)
    down = jouk * closed_fraction * (1.0 + surge_margin)
    hmin = h0 - down
    temp = rig_temperature_c(rig)
    pv = vapour_pressure_pa(temp)
    hv = rig_vapour_head_m(rig, p_atm_pa)
    allowed = hmin > hv
    detail = (f"predicted downsurge minimum {hmin:.1f} m = steady {h0:.1f} m - Joukowsky {down:.1f} m "
              f"(Q0 {q0 * 1e3:.3g} l/s, margin {surge_margin:.0%})")
    vap = f"the vapour-pressure head {hv:.2f} m ({pv / 1e3:.2f} kPa at {temp:g} C)"
    if allowed:
        msg = f"{detail} stays above {vap}"
    else:
        msg = (f"manoeuvre refused: cavitation (column separation): {detail} reaches {vap}; "
               f"raise the reservoir head or lower the flow")
    return DownsurgePrediction(h0, q0, down, hmin, hv, temp, allowed, msg)


@dataclass(frozen=True)
class CavitationFinding:
    """Samples of a record within the margin of the vapour-pressure head."""

    samples: int
    first_s: float  # time of the first and last such sample (as the record's axis gives it)
    last_s: float
    min_head_m: float
    vapour_head_m: float
    margin_m: float

    def message(self) -> str:
        return (f"the head reaches the vapour-pressure head ({self.vapour_head_m:.2f} m; lowest {self.min_head_m:.2f} m) "
                f"in {self.samples} samples from t = {self.first_s:.3f} s to {self.last_s:.3f} s: the water column "
                f"separated (cavitation) and the model does not hold there; its parameters are not the pipe's")


def cavitating(t_s, head_m, vapour_head: float, margin_m: float = DETECTION_MARGIN_M) -> CavitationFinding | None:
    """The samples of ``head_m`` (absolute gauge head, m) at or below vapour_head + margin, or None."""
    h = np.asarray(head_m, dtype=float)
    with np.errstate(invalid="ignore"):
        low = h <= vapour_head + margin_m
    idx = np.flatnonzero(low)
    if idx.size == 0:
        return None
    t = np.asarray(t_s, dtype=float)
    return CavitationFinding(int(idx.size), float(t[idx[0]]), float(t[idx[-1]]), float(np.nanmin(h[idx])),
                             float(vapour_head), float(margin_m))
