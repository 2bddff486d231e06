"""What is physical: the one place that bounds every number and every count an input can set.

Every input enters through one of four doors -- a TOML config (:mod:`velab.config`), a CSV
import (:mod:`velab.csvimport`), a run file read back (:mod:`velab.runfiles.reader`: the stored
rig, manoeuvre, data and their types) and a CLI argument (:mod:`velab.commands`) -- and each
door checks the same bounds, from here, so ``synth``, ``import``, ``fit`` and ``record`` follow
one rule. The bounds come from the physics of a water-hammer bench, with a wide margin: wave
speeds a water-filled pipe can have, closure times an actuator can make, sampling steps a DAQ
can take, heads a transducer can read. A value outside them is not a rig but a typing error
(``1e29``) or a file read with the wrong units, and is refused in one line naming the key.

The counts (transducers, channels, Kelvin-Voigt elements, samples, table points) are sized from
what a real bench has, so that no input makes a command run for minutes.

Leaf module (standard library only): the device layer and ``velab --help`` may import it.

    reason = WAVE_SPEED_M_S(1e29)        # "must be in [20, 2000] m/s (...)", or None
    problem = rig_problem(rig)           # ("[pipe] length_m", reason) or None
"""

from __future__ import annotations

import math
from dataclasses import dataclass

GRAVITY_M_S2 = 9.81


@dataclass(frozen=True)
class Bound:
    """A closed interval [lo, hi] in ``units`` (``lo_open``: (lo, hi]); ``why``: the physics, for the message.

    Called with a value it returns None when the value is inside, else the reason (a
    :mod:`velab.tomlschema` check, so a config key takes it as ``Key(float, check=BOUND)``).
    """

    lo: float
    hi: float
    units: str = ""
    why: str = ""
    lo_open: bool = False

    def contains(self, v) -> bool:
        try:
            v = float(v)
        except (TypeError, ValueError, OverflowError):
            return False
        if not math.isfinite(v):
            return False
        return (v > self.lo if self.lo_open else v >= self.lo) and v <= self.hi

    def __call__(self, v) -> str | None:
        if self.contains(v):
            return None
        u = f" {self.units}" if self.units else ""
        why = f" ({self.why})" if self.why else ""
        left = "(" if self.lo_open else "["
        return f"must be in {left}{self.lo:g}, {self.hi:g}]{u}{why}"

    def describe(self) -> str:
        left = "(" if self.lo_open else "["
        return f"{left}{self.lo:g}, {self.hi:g}]{' ' + self.units if self.units else ''}"


# ------------------------------------------------------------------ the pipe and its water
PIPE_LENGTH_M = Bound(0.5, 20_000.0, "m", "a laboratory rig or a pipeline")
PIPE_DIAMETER_M = Bound(0.002, 3.0, "m", "a pipe's bore")
WALL_THICKNESS_M = Bound(1e-4, 0.3, "m", "a pipe's wall")
# a pressure wave in water travels below water's own sound speed (1480 m/s at 20 C, a rigid pipe) and,
# in the softest wall that holds water, above a few tens of m/s
WAVE_SPEED_M_S = Bound(20.0, 2000.0, "m/s", "wave speeds a water-filled pipe can have")
# L / a: the time a wave takes along the pipe; it sets the model's grid (and its work)
WAVE_TRAVEL_S = Bound(1e-3, 30.0, "s", "the wave's travel time L / a along the pipe")
DENSITY_KG_M3 = Bound(500.0, 2000.0, "kg/m3", "a liquid")
KINEMATIC_VISCOSITY_M2_S = Bound(1e-7, 1e-3, "m2/s", "a liquid")
STEADY_FLOW_M3_S = Bound(1e-7, 20.0, "m3/s", "a steady flow a valve can shut")
MEAN_VELOCITY_M_S = Bound(1e-5, 30.0, "m/s", "the steady mean velocity Q0 / A")
RESERVOIR_HEAD_M = Bound(0.0, 2000.0, "m", "a reservoir or air vessel's head", lo_open=True)

# ------------------------------------------------------------------ the manoeuvre
# Q(t) = Q0 / (1 + exp(beta t + gamma)); 90 % -> 10 % of Q0 in ln(81)/beta: from 0.44 ms (beta 1e4)
# to 73 min (beta 1e-3), far past what a valve actuator can make at either end.
BETA_PER_S = Bound(1e-3, 1e4, "1/s", "a closure 90 -> 10 % in 0.44 ms to 73 min")
# the closure starts at the trigger: the valve at least half open there (gamma <= 0), and exp(-gamma)
# beyond double precision's reach is the same sigmoid as exp(100)
GAMMA = Bound(-100.0, 0.0, "", "the valve at least half open at the trigger")
HALF_CLOSURE_S = Bound(0.0, 3600.0, "s", "the half closure -gamma/beta within an hour of the trigger")

# ------------------------------------------------------------------ the transducer and the data
FULL_SCALE_BAR = Bound(0.01, 2000.0, "bar", "a pressure transducer's range")
ACCURACY_FS = Bound(0.0, 0.1, "", "a transducer's accuracy, as a fraction of its full scale")
# sampling steps a DAQ can take: 1 us (1 MHz) to 10 s
SAMPLE_RATE_HZ = Bound(0.1, 1e6, "Hz", "a DAQ's sampling rate, steps of 1 us to 10 s")
# no head a water-hammer rig can see comes near 10 kbar; a value beyond is a wrong unit or a wrong file
HEAD_M = Bound(-1e5, 1e5, "m", "heads of water a pipe can hold")
# the vacuum is -10.3 m of gauge head; a transducer reads up to its full scale and clips not far above it
VACUUM_HEAD_M = -10.4
OVER_RANGE = 1.5  # a reading beyond 1.5 x the full scale is not a reading of this transducer

# ------------------------------------------------------------------ the wall
MODULUS_PA = Bound(1e5, 1e14, "Pa", "a Kelvin-Voigt spring")
VISCOSITY_PA_S = Bound(1e2, 1e20, "Pa.s", "a Kelvin-Voigt dashpot")
RETARDATION_S = Bound(1e-6, 1e7, "s", "a retardation time")

# ------------------------------------------------------------------ counts a real bench has
MAX_TRANSDUCERS = 32  # pressure transducers along one pipe
MAX_KV_ELEMENTS = 12  # Kelvin-Voigt elements of a material (the fits go up to S6)
MAX_CHANNELS = 64  # fast channels of a run file
MAX_TABLE_POINTS = 1000  # points of a valve's characteristic table
MAX_SAMPLES = 50_000_000  # samples of one record (10 kHz for 83 minutes)
MAX_RUNS = 10_000  # run files on one command line
# the time-domain model's work: grid cells x time steps of one model run (about a minute of CPU)
MAX_MOC_CELL_STEPS = 2e9


def check_count(n: int, limit: int, what: str) -> str | None:
    """None when ``n`` <= ``limit``, else the reason naming the real bench's size."""
    return None if n <= limit else f"{n} {what}, more than the {limit} a bench has"


def rig_problem(rig) -> tuple[str, str] | None:
    """The first value of ``rig`` (a :class:`velab.rig.Rig`) outside the bounds, as ``(key, reason)`` with
    the key labelled as in a rig file ("[pipe] length_m"); None for a physical rig."""
    p, m = rig.pipe, rig.manoeuvre
    checks = (
        ("[pipe] length_m", PIPE_LENGTH_M, p.length_m),
        ("[pipe] inner_diameter_m", PIPE_DIAMETER_M, p.inner_diameter_m),
        ("[pipe] wall_thickness_m", WALL_THICKNESS_M, p.wall_thickness_m),
        ("[fluid] density_kg_m3", DENSITY_KG_M3, rig.fluid.density_kg_m3),
        ("[fluid] kinematic_viscosity_m2_s", KINEMATIC_VISCOSITY_M2_S, rig.fluid.kinematic_viscosity_m2_s),
        ("[flow] steady_flow_m3_s", STEADY_FLOW_M3_S, rig.steady_flow_m3_s),
        ("[flow] reservoir_head_m", RESERVOIR_HEAD_M, rig.reservoir_head_m),
        ("[manoeuvre] beta_per_s", BETA_PER_S, m.beta_per_s),
        ("[manoeuvre] gamma", GAMMA, m.gamma),
        ("[transducer] full_scale_bar", FULL_SCALE_BAR, rig.transducer.full_scale_pa / 1e5),
        ("[transducer] accuracy_fs", ACCURACY_FS, rig.transducer.accuracy_fs),
        ("[wave] nominal_speed_m_s", WAVE_SPEED_M_S, rig.nominal_wave_speed_m_s),
    )
    for key, bound, value in checks:
        reason = bound(value)
        if reason:
            return key, f"{reason} (got {value:g})" if _is_number(value) else reason
    if not p.wall_thickness_m < p.inner_diameter_m / 2:
        return "[pipe] wall_thickness_m", f"must be less than half the inner diameter (got {p.wall_thickness_m:g})"
    derived = (
        ("[flow] steady_flow_m3_s", MEAN_VELOCITY_M_S, rig.steady_flow_m3_s / p.area_m2, "mean velocity", "m/s"),
        ("[pipe] length_m", WAVE_TRAVEL_S, p.length_m / rig.nominal_wave_speed_m_s, "L / a", "s"),
        ("[manoeuvre] gamma", HALF_CLOSURE_S, -m.gamma / m.beta_per_s, "half closure", "s"),
    )
    for key, bound, value, name, units in derived:
        reason = bound(value)
        if reason:
            return key, f"{name} {value:.3g} {units}: {reason}"
    count = check_count(len(rig.transducers), MAX_TRANSDUCERS, "[[transducers]] tables")
    if count:
        return "[[transducers]]", count
    for i, s in enumerate(rig.transducers):
        if not (_is_number(s.position_m) and 0 < s.position_m <= p.length_m):
            return (f"[[transducers]] #{i + 1} position_m",
                    f"must be in (0, {p.length_m:g}] m (from the reservoir), got {s.position_m}")
    return None


def material_problem(material) -> tuple[str, str] | None:
    """The first value of a :class:`velab.config.Material` outside the bounds, as ``(key, reason)``."""
    reason = WAVE_SPEED_M_S(material.wave_speed_m_s)
    if reason:
        return "wave_speed_m_s", f"{reason} (got {material.wave_speed_m_s:g})"
    count = check_count(len(material.elements), MAX_KV_ELEMENTS, "[[kelvin_voigt]] elements")
    if count:
        return "[[kelvin_voigt]]", count
    for i, el in enumerate(material.elements):
        for key, bound, value in (("E_pa", MODULUS_PA, el.E_pa), ("eta_pa_s", VISCOSITY_PA_S, el.eta_pa_s),
                                  ("tau_s", RETARDATION_S, el.eta_pa_s / el.E_pa if el.E_pa else math.inf)):
            reason = bound(value)
            if reason:
                return f"[[kelvin_voigt]] #{i + 1} {key}", f"{reason} (got {value:g})"
    return None


def moc_cell_steps(rig, duration_s: float) -> float:
    """The time-domain model's work for ``duration_s`` of record on ``rig``: reaches x steps
    (velab.moc.head: N = L / (a dt) reaches of step dt = min(2 ms, 1 / (12 beta)))."""
    dt = min(0.002, 1.0 / (12.0 * rig.manoeuvre.beta_per_s))
    reaches = max(2.0, rig.pipe.length_m / (rig.nominal_wave_speed_m_s * dt))
    return reaches * (duration_s / dt)


def work_problem(rig, duration_s: float) -> str | None:
    """None when one model run of ``duration_s`` on ``rig`` is bounded work, else the reason."""
    work = moc_cell_steps(rig, duration_s)
    if work <= MAX_MOC_CELL_STEPS:
        return None
    return (f"{duration_s:g} s on rig {rig.name} is {work:.3g} grid cells x steps of the time-domain model, more "
            f"than the {MAX_MOC_CELL_STEPS:.3g} one run may take (a {rig.pipe.length_m:g} m pipe, closure "
            f"beta {rig.manoeuvre.beta_per_s:g} 1/s): shorten the record")


def head_range_m(rig) -> tuple[float, float]:
    """The heads (m) the rig's transducer can read: from the vacuum to OVER_RANGE x its full scale."""
    fs_m = rig.transducer.full_scale_pa / (rig.fluid.density_kg_m3 * GRAVITY_M_S2)
    return VACUUM_HEAD_M, OVER_RANGE * fs_m


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)
