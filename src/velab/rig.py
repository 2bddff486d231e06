"""The rig as typed, immutable data: pipe, fluid, steady flow, manoeuvre, transducer, friction laws.

Loaded from TOML by :func:`velab.config.load_rig`; stored in run files as JSON
(:meth:`Rig.to_dict`, :func:`rig_from_dict`). The derived quantities carry the
names of physics.md (Reynolds number, Darcy f, tangent resistance R, Joukowsky head).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace

from velab.errors import ConfigError
from velab.friction import FACTOR_LAWS, LAMINAR_RE, STEADY_LAWS, UNSTEADY_LAWS, darcy_factor
from velab.valvelaw import Valve, commanded_time_s, valve_from_dict

GRAVITY_M_S2 = 9.81


@dataclass(frozen=True)
class Pipe:
    length_m: float
    inner_diameter_m: float
    wall_thickness_m: float
    constraint_alpha: float
    material: str = ""
    pressure_rating_pa: float | None = None

    @property
    def area_m2(self) -> float:
        return math.pi * self.inner_diameter_m**2 / 4.0


@dataclass(frozen=True)
class Fluid:
    density_kg_m3: float = 998.2
    kinematic_viscosity_m2_s: float = 1.004e-6
    temperature_c: float = 20.0  # sets the vapour-pressure head (velab.cavitation); stored rigs without it: 20 C


@dataclass(frozen=True)
class Manoeuvre:
    """The valve closure Q(t) = Q0 / (1 + exp(beta t + gamma)), t >= 0 from the trigger."""

    beta_per_s: float = 32.0
    gamma: float = -5.5

    @property
    def half_closure_s(self) -> float:
        return -self.gamma / self.beta_per_s

    @property
    def closure_time_s(self) -> float:
        """90 % -> 10 % of Q0."""
        return math.log(81.0) / self.beta_per_s

    @property
    def closed_s(self) -> float:
        """When the commanded sigmoid has 0.1 % of Q0 left (s from the trigger; 0 if it starts there)."""
        return max(0.0, float(commanded_time_s(0.1, self.beta_per_s, self.gamma)))


@dataclass(frozen=True)
class Transducer:
    full_scale_pa: float = 6.0e5
    accuracy_fs: float = 0.0015


VALVE_SECTION = "valve"  # the name of the one transducer of a rig without a [[transducers]] table


@dataclass(frozen=True)
class Section:
    """A pressure transducer along the pipe: its name and its distance from the upstream reservoir
    (0 < x <= L; the valve's is at L). A ``[[transducers]]`` table of the rig file."""

    name: str
    position_m: float


@dataclass(frozen=True)
class FitSettings:
    """Optional ``[fit]`` table of a rig file: the calibration's retardation-time bounds (s).

    None: derived from the data (velab.fitting.params.derive_bounds). ``velab fit
    --tau-min/--tau-max`` and ``fit_sweep(tau_min_s=, tau_max_s=)`` take precedence.
    """

    tau_min_s: float | None = None
    tau_max_s: float | None = None


@dataclass(frozen=True)
class Rig:
    """Reservoir - pipe - valve rig (physics.md section 1)."""

    name: str
    pipe: Pipe
    fluid: Fluid
    steady_flow_m3_s: float
    reservoir_head_m: float
    manoeuvre: Manoeuvre
    transducer: Transducer
    nominal_wave_speed_m_s: float
    # Friction (velab.friction; docs/model.md): the steady law of the transient
    # ("quadratic" Darcy-Weisbach, "linear" its tangent at Q0 as in the paper, "none"),
    # how f is computed ("blasius" smooth, "colebrook" with roughness_m), frozen at the
    # steady Reynolds number, and the unsteady friction ("none", "vardy-brown"
    # weighting function, "brunone" instantaneous acceleration with brunone_k3).
    friction: str = "quadratic"
    friction_factor_law: str = "blasius"
    roughness_m: float = 0.0
    friction_unsteady: str = "none"
    brunone_k3: float = 0.02
    source: str = ""
    fit: FitSettings = field(default_factory=FitSettings)  # the [fit] table (velab.fitting)
    # the valve pair and its flow law (velab.valvelaw, physics.md section 10): the [valve] table
    valve: Valve = field(default_factory=Valve)
    # the pressure transducers along the pipe ([[transducers]]); empty: the one at the valve (``sections``)
    transducers: tuple[Section, ...] = ()

    def __post_init__(self):
        for name, value, allowed in (("friction", self.friction, STEADY_LAWS),
                                     ("friction_factor_law", self.friction_factor_law, FACTOR_LAWS),
                                     ("friction_unsteady", self.friction_unsteady, UNSTEADY_LAWS)):
            if value not in allowed:
                raise ValueError(f"{name} must be one of {', '.join(allowed)}, got {value!r}")
        if not (self.roughness_m >= 0 and self.brunone_k3 >= 0):
            raise ValueError("roughness_m and brunone_k3 must not be negative")

    @property
    def sections(self) -> tuple[Section, ...]:
        """The rig's transducers, the one at the valve ("valve", x = L) when the rig names none."""
        return self.transducers or (Section(VALVE_SECTION, self.pipe.length_m),)

    @property
    def head_section(self) -> Section:
        """The transducer whose head is a run's ``head`` channel (what a single fit reads): the first at
        the valve, else the first listed."""
        at_valve = [s for s in self.sections if s.position_m == self.pipe.length_m]
        return (at_valve or list(self.sections))[0]

    def section_channel(self, section: Section) -> str:
        """A transducer's channel in a run file: ``head`` for :attr:`head_section`, else ``head_<name>``."""
        return "head" if section == self.head_section else f"head_{section.name}"

    def steady_head_at_m(self, position_m: float) -> float:
        """The steady head at a distance x from the reservoir: the friction loss grows linearly along the pipe."""
        return self.reservoir_head_m - self.steady_head_loss_m * position_m / self.pipe.length_m

    # ---- derived quantities, named as in physics.md
    @property
    def reynolds(self) -> float:
        v = self.steady_flow_m3_s / self.pipe.area_m2
        return abs(v) * self.pipe.inner_diameter_m / self.fluid.kinematic_viscosity_m2_s

    @property
    def laminar(self) -> bool:
        """Steady flow below Re 2300: Poiseuille friction, Zielke's weighting function."""
        return self.reynolds < LAMINAR_RE

    @property
    def friction_factor(self) -> float:
        """Darcy f at the steady state (frozen at Re of Q0): 64/Re, Blasius or Colebrook; 0 for friction "none"."""
        if self.friction == "none":
            return 0.0
        return darcy_factor(self.reynolds, self.friction_factor_law, self.roughness_m / self.pipe.inner_diameter_m)

    @property
    def linear_resistance(self) -> float:
        """Tangent R = dJ/dQ at Q0 of the steady law, s/m^3 per metre of pipe (0 for friction "none").

        Turbulent (f frozen): R = f Q0 / (g D A^2), twice the secant J0/Q0. Laminar: the
        Poiseuille law is linear, R = f Q0 / (2 g D A^2) = 32 nu / (g D^2 A).
        """
        p = self.pipe
        R = self.friction_factor * self.steady_flow_m3_s / (GRAVITY_M_S2 * p.inner_diameter_m * p.area_m2**2)
        return R / 2 if self.laminar else R

    @property
    def friction_description(self) -> str:
        """One line for reports: the laws and the numbers they give on this rig."""
        if self.friction == "none":
            steady = "none (frictionless pipe)"
        else:
            law = {"quadratic": "quadratic (Darcy-Weisbach f Q|Q|/(2gDA^2))",
                   "linear": "linear (tangent R = f Q0/(gDA^2), the paper's)"}[self.friction]
            f_law = ("64/Re (laminar)" if self.laminar else "Blasius" if self.friction_factor_law == "blasius"
                     else f"Colebrook-White, roughness {self.roughness_m * 1e3:g} mm")
            steady = f"{law}, f = {self.friction_factor:.4g} {f_law} at Re {self.reynolds:.0f} (frozen)"
        unsteady = {"none": "no unsteady friction",
                    "vardy-brown": "unsteady " + ("Zielke" if self.laminar else "Vardy-Brown") + " weighting function",
                    "brunone": f"unsteady Brunone k3 = {self.brunone_k3:g}"}[self.friction_unsteady]
        return f"{steady}; {unsteady}"

    @property
    def steady_head_loss_m(self) -> float:
        p = self.pipe
        return self.friction_factor * p.length_m * self.steady_flow_m3_s**2 / (
            2 * GRAVITY_M_S2 * p.inner_diameter_m * p.area_m2**2
        )

    @property
    def steady_head_m(self) -> float:
        """Head at the transducer (just upstream of the valve) before the trigger."""
        return self.reservoir_head_m - self.steady_head_loss_m

    @property
    def valve_head_m(self) -> float:
        """Hv0: the steady head just upstream of the valve above its free discharge (the valve pair
        discharges at the transducer's level, so this is the steady head at the transducer)."""
        return self.steady_head_m

    def joukowsky_head_m(self, wave_speed_m_s: float | None = None) -> float:
        a = wave_speed_m_s or self.nominal_wave_speed_m_s
        return a * self.steady_flow_m3_s / (GRAVITY_M_S2 * self.pipe.area_m2)

    def with_changes(self, **changes) -> "Rig":
        return replace(self, **changes)

    def to_dict(self) -> dict:
        return asdict(self)


def constraint_coefficient(anchoring: str, poisson: float, d: float, e: float, thick: bool) -> float:
    """Pipe constraint coefficient alpha (Wylie & Streeter), thin- or thick-walled form."""
    if not thick:
        return {"upstream": 1 - poisson / 2, "throughout": 1 - poisson**2, "expansion_joints": 1.0}[anchoring]
    base = {"upstream": 1 - poisson / 2, "throughout": 1 - poisson**2, "expansion_joints": 1.0}[anchoring]
    return (2 * e / d) * (1 + poisson) + d * base / (d + e)


def rig_from_dict(d: dict) -> Rig:
    """Inverse of :meth:`Rig.to_dict` (run files store the rig as JSON)."""
    try:
        return Rig(
            name=d["name"],
            pipe=Pipe(**d["pipe"]),
            fluid=Fluid(**d["fluid"]),
            steady_flow_m3_s=float(d["steady_flow_m3_s"]),
            reservoir_head_m=float(d["reservoir_head_m"]),
            manoeuvre=Manoeuvre(**d["manoeuvre"]),
            transducer=Transducer(**d["transducer"]),
            nominal_wave_speed_m_s=float(d["nominal_wave_speed_m_s"]),
            **_friction_from_dict(d),
            source=d.get("source", ""),
            fit=FitSettings(**(d.get("fit") or {})),
            valve=_valve_from_stored(d),
            transducers=tuple(Section(name=str(x["name"]), position_m=float(x["position_m"]))
                              for x in d.get("transducers") or ()),
        )
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise ConfigError(f"rig description: invalid or incomplete ({exc})") from None


def checked_rig(rig: Rig, where: str = "rig description") -> Rig:
    """``rig`` if it is physical by :mod:`velab.bounds` (the rule a rig file is read with), else a one-line
    ConfigError naming ``where`` and the key: a stored rig is checked as its file was."""
    from velab import bounds

    try:
        problem = bounds.rig_problem(rig)
    except (TypeError, ValueError, ZeroDivisionError, OverflowError) as exc:
        problem = ("", f"not a number where one is needed ({exc})")
    if problem:
        raise ConfigError(f"{where}: {problem[0]}: {problem[1]}" if problem[0] else f"{where}: {problem[1]}")
    return rig

def _valve_from_stored(d: dict) -> Valve:
    """The valve of a stored rig. Run files written before the valve law existed were made with the
    flow imposed as the commanded sigmoid (synthetic runs, the simulated rig), or hold records whose
    valve nobody described (imports): they read as the paper's imposed flow."""
    if "valve" not in d:
        return Valve(law="imposed", characteristic="linear")
    return valve_from_dict(d["valve"])


def _friction_from_dict(d: dict) -> dict:
    """Friction fields of a stored rig. Run files written before quadratic friction existed
    store only ``"friction": "blasius"`` (the tangent R with Blasius f) or ``"none"``."""
    law = d.get("friction", "blasius")
    out = {"friction": "linear" if law == "blasius" else law,
           "friction_factor_law": d.get("friction_factor_law", "blasius"),
           "roughness_m": float(d.get("roughness_m", 0.0)),
           "friction_unsteady": d.get("friction_unsteady", "none"),
           "brunone_k3": float(d.get("brunone_k3", 0.02))}
    return out
