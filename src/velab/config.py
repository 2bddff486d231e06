"""Rig and material configuration: TOML files loaded into immutable, typed objects.

Units are part of every key name (``length_m``, ``steady_flow_m3_s``,
``E_pa``, ``eta_pa_s`` ...). Every error names the file, the key and the reason,
on one line, so that an operator can fix the file without reading code.

Configurations are addressed by short names or paths: ``load_rig("perugia")``
reads ``rigs/perugia.toml`` from the first config folder that has it (a lab's
folders in ``$VELAB_CONFIG_PATH``, ``~/.config/velab``, then the built-in
``velab.configs``; see :mod:`velab.configpath`). A path to any TOML file works
everywhere a name does. Files are read and checked by :mod:`velab.tomlschema`.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path

from velab import bounds
from velab.configpath import config_stem, load_config
from velab.friction import FACTOR_LAWS, STEADY_LAWS, UNSTEADY_LAWS
from velab.rig import FitSettings, Fluid, Manoeuvre, Pipe, Rig, Section, Transducer, constraint_coefficient
# One validation machinery for every config (velab.tomlschema); the short names keep this module's schema readable.
from velab.tomlschema import Key as _Key
from velab.tomlschema import Reader as _Reader
from velab.tomlschema import non_negative as _non_negative
from velab.tomlschema import positive as _positive
from velab.valvelaw import CHARACTERISTICS, DEFAULT_SERIES_SHARE, VALVE_LAWS, Valve, check_table

log = logging.getLogger("velab.config")

# Retardation times of the paper's "reduced" Sm: the first m of these are fixed.
REDUCED_RETARDATION_TIMES_S = (0.01, 0.1, 1.0, 10.0, 100.0)

# Paper's bounds for the calibrated spring moduli and viscosities (Pa, Pa s).
MODULUS_BOUNDS_PA = (1e6, 1e12)
VISCOSITY_BOUNDS_PA_S = (1e6, 1e12)


# --------------------------------------------------------------------------- schema


def _fraction(v: float) -> str | None:
    return None if 0 <= v < 0.5 else "must be in [0, 0.5)"


def _alpha(v: float) -> str | None:
    return None if 0 < v <= 2 else "must be in (0, 2]"



# --------------------------------------------------------------------------- rig files


_ANCHORING = ("upstream", "throughout", "expansion_joints")


def load_rig(name_or_path: str | os.PathLike) -> Rig:
    path, doc = load_config("rigs", name_or_path)
    r = _Reader(path, doc)
    _check_tables(r, doc, RIG_TABLES)
    top = r.read(
        {k: v for k, v in doc.items() if not isinstance(v, dict) and k != "transducers"},
        "",
        {"name": _Key(str, False, config_stem(path)), "description": _Key(str, False, "")},
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
            # the water's temperature: its vapour pressure is the interlock's cavitation limit (velab.cavitation)
            "temperature_c": _Key(float, False, 20.0, _water_temperature),
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
    valve = _valve_keys(r)
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
        valve=valve,
        transducers=_transducers(r, pipe["length_m"]),
    )
    try:  # derived quantities of absurd (if finite) inputs can overflow: a config error, not a crash
        steady_head_m = rig.steady_head_m
        finite = math.isfinite(steady_head_m) and math.isfinite(rig.joukowsky_head_m())
    except (OverflowError, ZeroDivisionError, ValueError):
        finite = False
    if not finite:
        raise r.fail("[flow]", "non-physical rig: the steady or Joukowsky head is not a finite number")
    if steady_head_m <= 0:
        raise r.fail("[flow] reservoir_head_m", f"smaller than the steady head loss {rig.steady_head_loss_m:.3g} m")
    problem = bounds.rig_problem(rig)  # the one rule of what is physical (velab.bounds), as for a stored rig
    if problem:
        raise r.fail(*problem)
    return rig


# The tables a rig file may have (and its [[transducers]] array): any other is refused, a misspelt one named.
RIG_TABLES = ("pipe", "fluid", "flow", "manoeuvre", "transducer", "wave", "fit", "valve", "transducers")


def _check_tables(r: "_Reader", doc: dict, known: tuple[str, ...]) -> None:
    """Refuse a table the file kind does not have: "unknown table [pipes] (did you mean [pipe]?)"."""
    import difflib

    for key in sorted(str(k) for k, v in doc.items() if isinstance(v, (dict, list)) and k not in known):
        value = doc[key]
        if isinstance(value, list) and not any(isinstance(x, dict) for x in value):
            continue  # an array value, not a table: the key check names it
        label = f"[[{key}]]" if isinstance(value, list) else f"[{key}]"
        close = difflib.get_close_matches(key, known, n=1, cutoff=0.6)
        hint = ""
        if close:
            hint = f" (did you mean [[{close[0]}]]?)" if close[0] == "transducers" else f" (did you mean [{close[0]}]?)"
        raise r.fail("", f"unknown table {label}{hint}; a rig file has "
                         f"{', '.join(f'[{t}]' for t in known if t != 'transducers')} and [[transducers]]")


def _transducers(r: "_Reader", length_m: float) -> tuple[Section, ...]:
    """The optional [[transducers]] tables: name and position_m (distance from the upstream reservoir,
    0 < x <= L, the valve's at L); names unique. None: the rig has the one at the valve (Rig.sections)."""
    tables = r.doc.get("transducers")
    if tables is None:
        return ()
    if not isinstance(tables, list) or not tables:
        raise r.fail("[[transducers]]", "must be one or more [[transducers]] tables")
    too_many = bounds.check_count(len(tables), bounds.MAX_TRANSDUCERS, "[[transducers]] tables")
    if too_many:  # before reading them: a bench has a few, a generated file may have thousands
        raise r.fail("[[transducers]]", too_many)
    out, names = [], set()
    for i, t in enumerate(tables):
        where = f"[[transducers]] #{i + 1} "
        if not isinstance(t, dict):
            raise r.fail(where, "must be a table")
        v = r.read(t, where, {"name": _Key(str), "position_m": _Key(float)})
        name, x = v["name"].strip(), v["position_m"]
        if not name or not all(c.isalnum() or c in "_-" for c in name):
            raise r.fail(where + "name", f"must be letters, digits, _ or - (it names a CSV column and a run file's "
                                         f"channel), got {v['name']!r}")
        if name in names:
            raise r.fail(where + "name", f"{name!r} is already the name of another transducer")
        if not 0 < x <= length_m:
            raise r.fail(where + "position_m", f"must be in (0, {length_m:g}] m (from the reservoir; the valve is at "
                                               f"the pipe's length), got {x:g}")
        names.add(name)
        out.append(Section(name, x))
    return tuple(out)


def _water_temperature(v: float) -> str | None:
    return None if 0 <= v <= 100 else "must be in [0, 100] C (liquid water at atmospheric pressure)"


def _share(v: float) -> str | None:
    return None if 0 < v <= 1 else "must be in (0, 1] (the valve's share of the steady head loss when open)"


def _valve_keys(r: "_Reader") -> Valve:
    """The optional [valve] table (velab.valvelaw): the flow law, MV's characteristic, its loss share."""
    table = r.table("valve", required=False) or {}
    v = r.read(
        table,
        "[valve] ",
        {
            "law": _Key(str, False, "orifice", choices=VALVE_LAWS),
            "series_loss_share": _Key(float, False, DEFAULT_SERIES_SHARE, _share),
            **CHARACTERISTIC_KEYS,
        },
    )
    return Valve(law=v["law"], series_loss_share=v["series_loss_share"], **_characteristic(r, v, "[valve]"),
                 characteristic_from="rig" if "characteristic" in table else "")


# MV's inherent flow characteristic: in the rig's [valve] table or in the valve's device profile
CHARACTERISTIC_KEYS = {
    "characteristic": _Key(str, False, "butterfly", choices=CHARACTERISTICS),
    "exponent": _Key(float, False, None, _positive),
    "position_pct": _Key(list, False, None),
    "flow_ratio": _Key(list, False, None),
}


def _characteristic(r: "_Reader", v: dict, where: str) -> dict:
    """The characteristic keys read into Valve's fields, checked together (one line naming the key)."""
    ch = v["characteristic"]
    if ch == "power" and v["exponent"] is None:
        raise r.fail(f"{where} exponent", 'missing key (needed with characteristic = "power")')
    if ch != "power" and v["exponent"] is not None:
        raise r.fail(f"{where} exponent", 'only used with characteristic = "power"')
    table = (v["position_pct"], v["flow_ratio"])
    if ch == "table":
        for key, val in zip(("position_pct", "flow_ratio"), table):
            if val is None:
                raise r.fail(f"{where} {key}", 'missing key (needed with characteristic = "table")')
            if len(val) > bounds.MAX_TABLE_POINTS:
                raise r.fail(f"{where} {key}", bounds.check_count(len(val), bounds.MAX_TABLE_POINTS, "points"))
            if not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in val):
                raise r.fail(f"{where} {key}", "must be an array of finite numbers")
        try:
            check_table(*table)
        except ValueError as exc:
            raise r.fail(f"{where} position_pct", str(exc)) from None
    elif any(x is not None for x in table):
        raise r.fail(f"{where} position_pct", 'only used with characteristic = "table"')
    return {"characteristic": ch, "exponent": v["exponent"],
            "position_pct": tuple(float(x) for x in table[0] or ()),
            "flow_ratio": tuple(float(x) for x in table[1] or ())}


def profile_characteristic(profile) -> dict | None:
    """The [valve] table of a valve actuator's device profile (the valve body's inherent characteristic,
    as the rig's [valve] keys ``characteristic``, ``exponent``, ``position_pct``, ``flow_ratio``) as
    Valve fields, or None when the profile has none. ConfigError naming the profile's file and key."""
    table = profile.sections.get("valve")
    if table is None:
        return None
    r = _Reader(profile.path or profile.name, {"valve": table})
    v = r.read(r.table("valve"), "[valve] ", CHARACTERISTIC_KEYS)
    if "characteristic" not in table:
        raise r.fail("[valve] characteristic", "missing key (the valve body's characteristic)")
    return _characteristic(r, v, "[valve]")


def with_valve_profile(rig: Rig, profile) -> Rig:
    """The rig with MV's characteristic from the valve's device profile, unless the rig file names its
    own (then the rig's wins: it describes this bench's assembly; the disagreement is logged). The
    characteristic's origin goes into the run file with the rig (``Valve.characteristic_from``)."""
    fields = profile_characteristic(profile)
    if fields is None:
        return rig
    name = f"profile {profile.name}"
    if rig.valve.characteristic_from == "rig":
        ours = replace(rig.valve, characteristic_from="")
        theirs = replace(rig.valve, **fields, characteristic_from="")
        if ours != theirs:
            log.warning("%s: the rig's [valve] characteristic (%s) differs from the valve's %s (%s): the rig's is used",
                        rig.source or rig.name, rig.valve.describe_characteristic(), name,
                        theirs.describe_characteristic())
        return rig
    return rig.with_changes(valve=replace(rig.valve, **fields, characteristic_from=name))


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
    path, doc = load_config("materials", name_or_path)
    return load_material_doc(path, doc)


def load_material_doc(path: Path, doc: dict) -> Material:
    r = _Reader(path, doc)
    top = r.read(
        doc,
        "",
        {
            "name": _Key(str, False, config_stem(path)),
            "description": _Key(str, False, ""),
            "wave_speed_m_s": _Key(float, check=_positive),
            "kelvin_voigt": _Key(list, False, []),
        },
    )
    too_many = bounds.check_count(len(top["kelvin_voigt"]), bounds.MAX_KV_ELEMENTS, "[[kelvin_voigt]] elements")
    if too_many:
        raise r.fail("[[kelvin_voigt]]", too_many)
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
    material = Material(wave_speed_m_s=top["wave_speed_m_s"], elements=tuple(elements), name=top["name"])
    problem = bounds.material_problem(material)  # velab.bounds: the same rule for files and stored materials
    if problem:
        raise r.fail(*problem)
    return material
