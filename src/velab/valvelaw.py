"""The valve as a bench makes the manoeuvre: position -> effective opening -> flow (physics.md section 10).

The actuator drives the butterfly valve MV along the commanded profile *in position* p(t) (% open);
the flow through the valve pair MV + DV (DV, the hand-operated throttle that sets Q0) discharging to
air follows the orifice law

    Q(t) = Q0 tau(t) sqrt((Hv0 + h(t)) / Hv0),    tau = 1 / sqrt((1 - s) + s / phi(p)^2),

with phi(p) = Cv(p) / Cv(100 %) MV's inherent flow characteristic, s MV's share of the steady head
loss when fully open, Hv0 the steady head just upstream of MV above the free discharge and h the head
rise there. The paper's model (``law = "imposed"``) instead imposes the flow itself as the sigmoid,
Q = Q0 / (1 + exp(beta t + gamma)): it is kept, named, to reproduce the paper's synthetic table.

This module is the one place where the position, the characteristic and the orifice law are
computed; the time-domain model (velab.moc), ``velab synth``, the simulated rig and the fit all use it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

VALVE_LAWS = ("orifice", "imposed")
# named inherent characteristics phi(p), p in % open: what a rig file may call them
CHARACTERISTICS = ("butterfly", "linear", "quick-opening", "power", "table")
_EXPONENTS = {"butterfly": 2.0, "linear": 1.0, "quick-opening": 0.5}
DEFAULT_SERIES_SHARE = 0.05  # MV's share of the steady loss when open (the reference rig: a few per cent)


@dataclass(frozen=True)
class Valve:
    """The valve pair of a rig: MV's characteristic, its share of the steady loss, the flow law.

    ``characteristic``: "butterfly" ((p/100)^2, the default: a butterfly passes most of its flow
    until the last third of its stroke), "linear", "quick-opening" ((p/100)^0.5), "power" (with
    ``exponent``) or "table" (``position_pct`` / ``flow_ratio``, interpolated monotonically).
    """

    law: str = "orifice"
    characteristic: str = "butterfly"
    series_loss_share: float = DEFAULT_SERIES_SHARE
    exponent: float | None = None
    position_pct: tuple[float, ...] = ()
    flow_ratio: tuple[float, ...] = ()
    # where the characteristic was given: "rig" (the rig file's [valve] table), "profile NAME" (the
    # valve's device profile, velab.config.with_valve_profile) or "" (not given: the default)
    characteristic_from: str = ""

    def __post_init__(self):
        if self.law not in VALVE_LAWS:
            raise ValueError(f"valve law must be one of {', '.join(VALVE_LAWS)}, got {self.law!r}")
        if self.characteristic not in CHARACTERISTICS:
            raise ValueError(f"valve characteristic must be one of {', '.join(CHARACTERISTICS)}, "
                             f"got {self.characteristic!r}")
        if not 0.0 < self.series_loss_share <= 1.0:
            raise ValueError(f"series_loss_share must be in (0, 1], got {self.series_loss_share}")
        if self.characteristic == "power" and not (self.exponent and self.exponent > 0):
            raise ValueError("a power characteristic needs a positive exponent")
        if self.characteristic == "table":
            check_table(self.position_pct, self.flow_ratio)

    @property
    def power(self) -> float | None:
        """The exponent n of phi = (p/100)^n, or None for a table."""
        if self.characteristic == "table":
            return None
        return float(self.exponent) if self.characteristic == "power" else _EXPONENTS[self.characteristic]

    def flow_ratio_at(self, position_pct) -> np.ndarray:
        """phi(p) = Cv(p)/Cv(100 %), p in % open (clipped to 0..100)."""
        x = np.clip(np.asarray(position_pct, dtype=float), 0.0, 100.0)
        n = self.power
        if n is not None:
            return (x / 100.0) ** n
        from scipy.interpolate import PchipInterpolator  # monotone, no overshoot

        return np.clip(PchipInterpolator(self.position_pct, self.flow_ratio)(x), 0.0, 1.0)

    def opening(self, position_pct) -> np.ndarray:
        """tau(p): the valve pair's effective opening (1 fully open, 0 shut)."""
        return effective_opening(self.flow_ratio_at(position_pct), self.series_loss_share)

    def describe_characteristic(self) -> str:
        return (f"table of {len(self.position_pct)} points" if self.characteristic == "table"
                else f"{self.characteristic} (p/100)^{self.power:g}")

    def describe(self) -> str:
        if self.law == "imposed":
            return "imposed sigmoid flow Q0 / (1 + exp(beta t + gamma)) (the paper's valve model)"
        origin = f" (from the valve's {self.characteristic_from})" if self.characteristic_from.startswith("profile") else ""
        return (f"orifice law through the valve pair: characteristic {self.describe_characteristic()}{origin}, the "
                f"valve's share of the steady loss {self.series_loss_share:g}")

    def to_dict(self) -> dict:
        return {"law": self.law, "characteristic": self.characteristic, "series_loss_share": self.series_loss_share,
                "exponent": self.exponent, "position_pct": list(self.position_pct),
                "flow_ratio": list(self.flow_ratio), "characteristic_from": self.characteristic_from}


def check_table(position_pct, flow_ratio) -> None:
    """A characteristic table: at least 2 points, positions increasing within 0..100 from 0 to 100,
    ratios non-decreasing from 0 at 0 % to 1 at 100 %. ValueError naming what is wrong."""
    p, r = list(position_pct), list(flow_ratio)
    if len(p) < 2 or len(p) != len(r):
        raise ValueError("a characteristic table needs position_pct and flow_ratio of equal length >= 2")
    if any(b <= a for a, b in zip(p, p[1:])) or p[0] != 0.0 or p[-1] != 100.0:
        raise ValueError("position_pct must increase strictly from 0 to 100")
    if any(b < a for a, b in zip(r, r[1:])) or r[0] != 0.0 or r[-1] != 1.0:
        raise ValueError("flow_ratio must not decrease, from 0 at 0 % open to 1 at 100 %")


def valve_from_dict(d: dict | None) -> Valve:
    """Inverse of :meth:`Valve.to_dict` (a run file's rig); None -> the default valve."""
    if not d:
        return Valve()
    return Valve(law=d.get("law", "orifice"), characteristic=d.get("characteristic", "butterfly"),
                 series_loss_share=float(d.get("series_loss_share", DEFAULT_SERIES_SHARE)),
                 exponent=d.get("exponent"), position_pct=tuple(d.get("position_pct") or ()),
                 flow_ratio=tuple(d.get("flow_ratio") or ()), characteristic_from=str(d.get("characteristic_from", "")))


def effective_opening(flow_ratio, series_loss_share: float) -> np.ndarray:
    """tau = 1 / sqrt((1 - s) + s / phi^2); 0 where phi = 0 (shut)."""
    phi = np.asarray(flow_ratio, dtype=float)
    s = float(series_loss_share)
    with np.errstate(divide="ignore", over="ignore"):
        inv = np.where(phi > 0, 1.0 / np.where(phi > 0, phi, 1.0) ** 2, np.inf)
    return np.where(phi > 0, 1.0 / np.sqrt((1.0 - s) + s * inv), 0.0)


def commanded_position_pct(t_s, beta_per_s: float, gamma: float, end_pct: float = 0.0) -> np.ndarray:
    """The commanded sigmoid in position: 100 % open before the trigger (t < 0), then
    end + (100 - end) / (1 + exp(beta t + gamma))."""
    t = np.asarray(t_s, dtype=float)
    arg = np.clip(beta_per_s * t + gamma, -700.0, 700.0)
    p = end_pct + (100.0 - end_pct) / (1.0 + np.exp(arg))
    return np.where(t >= 0, p, 100.0)


def commanded_time_s(opening_pct, beta_per_s: float, gamma: float):
    """The inverse of :func:`commanded_position_pct` during the stroke: when (s from its start) the commanded
    opening, as % of the stroke still to go, is ``opening_pct`` (0 < p < 100): (ln(100/p - 1) - gamma) / beta.
    Negative before the stroke's start (a sigmoid that starts below p)."""
    return (np.log(100.0 / np.asarray(opening_pct, dtype=float) - 1.0) - gamma) / beta_per_s


def orifice_coupling(head_rise_m, valve_head_m: float) -> np.ndarray:
    """sqrt((Hv0 + h) / Hv0): how the head rise upstream of the valve drives the flow (0 below the
    free discharge: no flow runs back in through a valve discharging to air)."""
    if not valve_head_m > 0 or not math.isfinite(valve_head_m):
        raise ValueError(f"the steady head above the discharge must be positive, got {valve_head_m}")
    return np.sqrt(np.maximum(1.0 + np.asarray(head_rise_m, dtype=float) / valve_head_m, 0.0))


def orifice_flow(opening, head_rise_m, steady_flow_m3_s: float, valve_head_m: float) -> np.ndarray:
    """Q = Q0 tau sqrt((Hv0 + h) / Hv0) (m^3/s)."""
    return steady_flow_m3_s * np.asarray(opening, dtype=float) * orifice_coupling(head_rise_m, valve_head_m)


def imposed_flow(position_pct, steady_flow_m3_s: float) -> np.ndarray:
    """The imposed law's flow for a valve position: Q = Q0 p / 100 (m^3/s), p clipped to 0..100 (the
    flow follows the command; the simulated rig before the orifice law, stored rigs without a valve)."""
    return steady_flow_m3_s * np.clip(np.asarray(position_pct, dtype=float), 0.0, 100.0) / 100.0
