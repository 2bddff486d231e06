"""Rig and material configuration: TOML files loaded into immutable, typed objects.

Units are part of every key name (``length_m``, ``steady_flow_m3_s``,
``E_pa``, ``eta_pa_s`` ...). Every error names the file, the key and the reason,
on one line, so that an operator can fix the file without reading code.

Built-in configurations live in the repository's ``configs/`` folder and are
addressed by short names: ``load_rig("perugia")`` reads
``configs/rigs/perugia.toml``; ``load_material("A")`` reads
``configs/materials/A.toml``. A path to any TOML file works everywhere a name does.
"""

from __future__ import annotations

import math
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from velab.errors import ConfigError
from velab.friction import FACTOR_LAWS, STEADY_LAWS, UNSTEADY_LAWS
# the rig's data classes live in velab.rig; re-exported here, where they always were
from velab.rig import (  # noqa: F401
    GRAVITY_M_S2,
    FitSettings,
    Fluid,
    Manoeuvre,
    Pipe,
    Rig,
    Transducer,
    constraint_coefficient,
    rig_from_dict,
)

# The repository's configs/ folder (editable install); VELAB_CONFIGS overrides it.
CONFIG_ROOT = Path(os.environ.get("VELAB_CONFIGS", Path(__file__).resolve().parents[2] / "configs"))

# Retardation times of the paper's "reduced" Sm: the first m of these are fixed.
REDUCED_RETARDATION_TIMES_S = (0.01, 0.1, 1.0, 10.0, 100.0)

# Paper's bounds for the calibrated spring moduli and viscosities (Pa, Pa s).
MODULUS_BOUNDS_PA = (1e6, 1e12)
VISCOSITY_BOUNDS_PA_S = (1e6, 1e12)


# --------------------------------------------------------------------------- schema


def _positive(v: float) -> str | None:
    return None if v > 0 else "must be positive"


def _non_negative(v: float) -> str | None:
    return None if v >= 0 else "must not be negative"


def _fraction(v: float) -> str | None:
    return None if 0 <= v < 0.5 else "must be in [0, 0.5)"


def _alpha(v: float) -> str | None:
    return None if 0 < v <= 2 else "must be in (0, 2]"


@dataclass(frozen=True)
class _Key:
    kind: type
    required: bool = True
    default: Any = None
    check: Callable[[Any], str | None] | None = None
    choices: tuple[str, ...] | None = None


class _Reader:
    """Reads one TOML document and raises ConfigError naming file and key."""

    def __init__(self, path: Path, doc: dict):
        self.path = path
        self.doc = doc

    def fail(self, where: str, reason: str) -> ConfigError:
        return ConfigError(f"{self.path}: {where}: {reason}")

    def table(self, name: str | None, required: bool = True) -> dict | None:
        if name is None:
            return self.doc
        t = self.doc.get(name)
        if t is None:
            if required:
                raise self.fail(f"[{name}]", "missing table")
            return None
        if not isinstance(t, dict):
            raise self.fail(f"[{name}]", f"must be a table, got {type(t).__name__}")
        return t

    def read(self, table: dict, where: str, spec: dict[str, _Key]) -> dict[str, Any]:
        unknown = sorted(set(table) - set(spec))
        if unknown:
            raise self.fail(
                f"{where}{unknown[0]}", f"unknown key (known: {', '.join(sorted(spec))})"
            )
        out = {}
        for key, k in spec.items():
            label = f"{where}{key}"
            if key not in table:
                if k.required:
                    raise self.fail(label, "missing key")
                out[key] = k.default
                continue
            out[key] = self.value(table[key], label, k)
        return out

    def value(self, v: Any, label: str, k: _Key) -> Any:
        if k.kind is float:
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise self.fail(label, f"must be a number, got {type(v).__name__} {v!r}")
            v = float(v)
            if not math.isfinite(v):
                raise self.fail(label, f"must be finite, got {v}")
        elif k.kind is int:
            if isinstance(v, bool) or not isinstance(v, int):
                raise self.fail(label, f"must be an integer, got {type(v).__name__} {v!r}")
        elif k.kind is str:
            if not isinstance(v, str):
                raise self.fail(label, f"must be a string, got {type(v).__name__} {v!r}")
            if k.choices and v not in k.choices:
                raise self.fail(label, f"must be one of {', '.join(k.choices)}, got {v!r}")
        elif k.kind is list:
            if not isinstance(v, list):
                raise self.fail(label, f"must be an array, got {type(v).__name__}")
        elif k.kind is bool:
            if not isinstance(v, bool):
                raise self.fail(label, f"must be true or false, got {v!r}")
        if k.check is not None:
            reason = k.check(v)
            if reason:
                raise self.fail(label, f"{reason} (got {v})")
        return v


def read_toml(path: str | os.PathLike) -> tuple[Path, dict]:
    """Parse a TOML file; a missing file or a syntax error is a ConfigError."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            return path, tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a directory, expected a TOML file") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: invalid TOML: {exc}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a text file") from None


def resolve(name_or_path: str | os.PathLike, kind: str) -> Path:
    """Map a built-in short name (``"A"``, ``"perugia"``) or a path to a file path."""
    p = Path(name_or_path)
    if p.suffix == ".toml" or p.exists() or len(p.parts) > 1:
        return p
    candidate = CONFIG_ROOT / kind / f"{name_or_path}.toml"
    if candidate.exists():
        return candidate
    known = sorted(f.stem for f in (CONFIG_ROOT / kind).glob("*.toml"))
    raise ConfigError(
        f"{name_or_path}: no such {kind[:-1]} file, and not a built-in one "
        f"(built-in: {', '.join(known) or 'none'})"
    )


# --------------------------------------------------------------------------- rig files


_ANCHORING = ("upstream", "throughout", "expansion_joints")


def load_rig(name_or_path: str | os.PathLike) -> Rig:
    path, doc = read_toml(resolve(name_or_path, "rigs"))
    r = _Reader(path, doc)
    top = r.read(
        {k: v for k, v in doc.items() if not isinstance(v, dict)},
        "",
        {"name": _Key(str, False, path.stem), "description": _Key(str, False, "")},
    )
    pipe = r.read(
        r.table("pipe"),
        "[pipe] ",
        {
            "length_m": _Key(float, check=_positive),
            "inner_diameter_m": _Key(float, check=_positive),
            "wall_thickness_m": _Key(float, check=_positive),
            "material": _Key(str, False, ""),
            "constraint_alpha": _Key(float, False, None, _alpha),
            "anchoring": _Key(str, False, None, choices=_ANCHORING),
            "poisson_ratio": _Key(float, False, None, _fraction),
            "thick_walled": _Key(bool, False, False),
            "pressure_rating_bar": _Key(float, False, None, _positive),
        },
    )
    if pipe["wall_thickness_m"] >= pipe["inner_diameter_m"] / 2:
        raise r.fail(
            "[pipe] wall_thickness_m",
            f"must be less than half the inner diameter (got {pipe['wall_thickness_m']} >= "
            f"{pipe['inner_diameter_m'] / 2})",
        )
    if pipe["constraint_alpha"] is not None:
        if pipe["anchoring"] is not None:
            raise r.fail("[pipe] anchoring", "give either constraint_alpha or anchoring + poisson_ratio, not both")
        alpha = pipe["constraint_alpha"]
    elif pipe["anchoring"] is not None:
        if pipe["poisson_ratio"] is None:
            raise r.fail("[pipe] poisson_ratio", "missing key (needed with anchoring)")
        alpha = constraint_coefficient(
            pipe["anchoring"], pipe["poisson_ratio"], pipe["inner_diameter_m"], pipe["wall_thickness_m"], pipe["thick_walled"]
        )
    else:
        raise r.fail("[pipe] constraint_alpha", "missing key (or give anchoring + poisson_ratio)")
    fluid = r.read(
        r.table("fluid", required=False) or {},
        "[fluid] ",
        {
            "density_kg_m3": _Key(float, False, 998.2, _positive),
            "kinematic_viscosity_m2_s": _Key(float, False, 1.004e-6, _positive),
        },
    )
    flow = r.read(
        r.table("flow"),
        "[flow] ",
        {
            "steady_flow_m3_s": _Key(float, check=_positive),
            "reservoir_head_m": _Key(float, check=_positive),
            # "blasius" is the name before quadratic friction existed: linear + Blasius f
            "friction": _Key(str, False, "quadratic", choices=STEADY_LAWS + ("blasius",)),
            "friction_factor": _Key(str, False, None, choices=FACTOR_LAWS),
            "roughness_m": _Key(float, False, None, _non_negative),
            "friction_unsteady": _Key(str, False, "none", choices=UNSTEADY_LAWS),
            "brunone_k3": _Key(float, False, None, _brunone_k3),
        },
    )
    friction = _friction_keys(r, flow, pipe["inner_diameter_m"])
    man = r.read(
        r.table("manoeuvre"),
        "[manoeuvre] ",
        {"beta_per_s": _Key(float, check=_positive), "gamma": _Key(float)},
    )
    tr = r.read(
        r.table("transducer"),
        "[transducer] ",
        {"full_scale_bar": _Key(float, check=_positive), "accuracy_fs": _Key(float, False, 0.0015, _non_negative)},
    )
    wave = r.read(r.table("wave"), "[wave] ", {"nominal_speed_m_s": _Key(float, check=_positive)})
    fit = r.read(
        r.table("fit", required=False) or {},
        "[fit] ",
        {"tau_min_s": _Key(float, False, None, _positive), "tau_max_s": _Key(float, False, None, _positive)},
    )
    if fit["tau_min_s"] is not None and fit["tau_max_s"] is not None and not fit["tau_min_s"] < fit["tau_max_s"]:
        raise r.fail("[fit] tau_max_s", f"must be greater than tau_min_s (got {fit['tau_max_s']} <= {fit['tau_min_s']})")
    rig = Rig(
        name=top["name"],
        pipe=Pipe(
            length_m=pipe["length_m"],
            inner_diameter_m=pipe["inner_diameter_m"],
            wall_thickness_m=pipe["wall_thickness_m"],
            constraint_alpha=alpha,
            material=pipe["material"],
            pressure_rating_pa=None if pipe["pressure_rating_bar"] is None else pipe["pressure_rating_bar"] * 1e5,
        ),
        fluid=Fluid(**fluid),
        steady_flow_m3_s=flow["steady_flow_m3_s"],
        reservoir_head_m=flow["reservoir_head_m"],
        manoeuvre=Manoeuvre(**man),
        transducer=Transducer(full_scale_pa=tr["full_scale_bar"] * 1e5, accuracy_fs=tr["accuracy_fs"]),
        nominal_wave_speed_m_s=wave["nominal_speed_m_s"],
        **friction,
        source=str(path),
        fit=FitSettings(**fit),
    )
    if rig.steady_head_m <= 0:
        raise r.fail("[flow] reservoir_head_m", f"smaller than the steady head loss {rig.steady_head_loss_m:.3g} m")
    return rig


def _brunone_k3(v: float) -> str | None:
    return None if 0 < v <= 0.2 else "must be in (0, 0.2] (measured values are 0.01-0.05)"


def _friction_keys(r: "_Reader", flow: dict, diameter_m: float) -> dict:
    """The [flow] friction keys -> Rig fields, rejecting contradictory combinations."""
    law, factor = flow["friction"], flow["friction_factor"]
    if law == "blasius":
        if factor not in (None, "blasius"):
            raise r.fail("[flow] friction", '"blasius" is the old name of friction = "linear" with '
                         'friction_factor = "blasius"; give friction = "linear" (or "quadratic") instead')
        law, factor = "linear", "blasius"
    factor = factor or "blasius"
    roughness = flow["roughness_m"]
    if factor == "colebrook":
        if roughness is None:
            raise r.fail("[flow] roughness_m", 'missing key (needed with friction_factor = "colebrook"; 0 = smooth)')
        if roughness > 0.05 * diameter_m:
            raise r.fail("[flow] roughness_m", f"must be at most 5 % of the inner diameter for Colebrook-White "
                         f"(got {roughness} m, D = {diameter_m} m)")
    elif roughness:
        raise r.fail("[flow] roughness_m", 'only used with friction_factor = "colebrook" (Blasius is a smooth pipe)')
    k3 = flow["brunone_k3"]
    if k3 is not None and flow["friction_unsteady"] != "brunone":
        raise r.fail("[flow] brunone_k3", 'only used with friction_unsteady = "brunone"')
    return {"friction": law, "friction_factor_law": factor, "roughness_m": roughness or 0.0,
            "friction_unsteady": flow["friction_unsteady"], "brunone_k3": 0.02 if k3 is None else k3}


# --------------------------------------------------------------------------- material


@dataclass(frozen=True)
class KelvinVoigt:
    """One Kelvin-Voigt element: spring E (Pa) parallel to dashpot eta (Pa s)."""

    E_pa: float
    eta_pa_s: float

    @property
    def tau_s(self) -> float:
        """Retardation time."""
        return self.eta_pa_s / self.E_pa

    @property
    def J_per_pa(self) -> float:
        """Creep compliance of the element."""
        return 1.0 / self.E_pa

    @classmethod
    def from_creep(cls, J_per_pa: float, tau_s: float) -> "KelvinVoigt":
        E = 1.0 / J_per_pa
        return cls(E_pa=E, eta_pa_s=E * tau_s)


@dataclass(frozen=True)
class Material:
    """Spring + m Kelvin-Voigt elements (Sm); m = 0 is the elastic pipe (EL).

    The spring E0 is represented by the wave speed a it produces in the rig.
    """

    wave_speed_m_s: float
    elements: tuple[KelvinVoigt, ...] = field(default_factory=tuple)
    name: str = ""

    @property
    def m(self) -> int:
        return len(self.elements)

    @property
    def model_name(self) -> str:
        return "EL" if self.m == 0 else f"S{self.m}"

    def creep_compliance(self, t_s, spring_compliance_per_pa: float = 0.0):
        """J(t) - J0 = sum_k J_k (1 - exp(-t/tau_k)) (plus J0 if given)."""
        import numpy as np

        t = np.asarray(t_s, dtype=float)
        out = np.full_like(t, spring_compliance_per_pa)
        for el in self.elements:
            out += el.J_per_pa * (1 - np.exp(-t / el.tau_s))
        return out

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "wave_speed_m_s": self.wave_speed_m_s,
            "kelvin_voigt": [{"E_pa": e.E_pa, "eta_pa_s": e.eta_pa_s} for e in self.elements],
        }


def material_from_dict(d: dict, where: str = "material") -> Material:
    """Inverse of :meth:`Material.to_dict` (for run files and JSON)."""
    return load_material_doc(Path(where), d)


def load_material(name_or_path: str | os.PathLike) -> Material:
    path, doc = read_toml(resolve(name_or_path, "materials"))
    return load_material_doc(path, doc)


def load_material_doc(path: Path, doc: dict) -> Material:
    r = _Reader(path, doc)
    top = r.read(
        doc,
        "",
        {
            "name": _Key(str, False, path.stem),
            "description": _Key(str, False, ""),
            "wave_speed_m_s": _Key(float, check=_positive),
            "kelvin_voigt": _Key(list, False, []),
        },
    )
    elements = []
    for i, el in enumerate(top["kelvin_voigt"]):
        where = f"[[kelvin_voigt]] #{i + 1} "
        if not isinstance(el, dict):
            raise r.fail(where.strip(), "must be a table")
        v = r.read(
            el,
            where,
            {
                "E_pa": _Key(float, False, None, _positive),
                "eta_pa_s": _Key(float, False, None, _positive),
                "J_per_pa": _Key(float, False, None, _positive),
                "tau_s": _Key(float, False, None, _positive),
            },
        )
        if v["E_pa"] is not None and v["eta_pa_s"] is not None and v["J_per_pa"] is None and v["tau_s"] is None:
            elements.append(KelvinVoigt(v["E_pa"], v["eta_pa_s"]))
        elif v["J_per_pa"] is not None and v["tau_s"] is not None and v["E_pa"] is None and v["eta_pa_s"] is None:
            elements.append(KelvinVoigt.from_creep(v["J_per_pa"], v["tau_s"]))
        else:
            raise r.fail(where.strip(), "give either E_pa + eta_pa_s or J_per_pa + tau_s")
    return Material(wave_speed_m_s=top["wave_speed_m_s"], elements=tuple(elements), name=top["name"])
