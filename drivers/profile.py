"""Device profiles: register maps, data types, word order, scaling and ranges, from TOML.

A profile lives in ``configs/devices/<name>.toml`` (or any path)::

    kind = "flowmeter"                 # which driver class reads it
    model = "Siemens SITRANS F M MAG 6000, Modbus RTU module"
    default_unit = 2
    word_order = "ABCD"                # default for multi-register values

    [registers.flow]                   # one table per register (PyMeasure style:
    table = "holding"                  #  the raw -> engineering conversion sits
    address = 3002                     #  next to the register it applies to)
    type = "float32"                   # uint16 int16 uint32 int32 float32 uint64 float64
    units = "m3/s"
    scale = 1.0                        # value = raw * scale + offset
    offset = 0.0
    min = -0.05                        # engineering range (reads: flags; writes: validation)
    max = 0.05
    access = "r"                       # "r" or "rw"
    # word_order = "CDAB"              # per-register override
    # bits = { 0 = "empty pipe", ... } # for bit fields
    # enum = { 0 = "idle", ... }       # for state registers

Any other top-level table (``[buffer]``, ``[channels.ch0]``, ``[limits]``) is kept
as a plain dict in ``profile.sections`` for the driver that owns the kind.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path

from velab.drivers.base import ProfileError
from velab.config import CONFIG_ROOT, read_toml
from velab.drivers.modbus import DATA_TYPES, WordOrder, decode_registers, encode_value, register_count
from velab.errors import ConfigError


def devices_dir() -> Path:
    return Path(CONFIG_ROOT) / "devices"


@dataclass(frozen=True)
class RegisterSpec:
    name: str
    address: int
    dtype: str = "uint16"
    table: str = "holding"
    units: str = ""
    scale: float = 1.0
    offset: float = 0.0
    word_order: WordOrder = WordOrder.ABCD
    access: str = "r"
    min: float | None = None
    max: float | None = None
    bits: dict = field(default_factory=dict)
    enum: dict = field(default_factory=dict)
    explicit_order: bool = False

    @property
    def count(self) -> int:
        return register_count(self.dtype)

    @property
    def scaled(self) -> bool:
        return self.scale != 1.0 or self.offset != 0.0

    def to_value(self, regs) -> float | int:
        raw = decode_registers(regs, self.dtype, self.word_order)
        return raw * self.scale + self.offset if self.scaled else raw

    def to_registers(self, value: float) -> list[int]:
        raw = (value - self.offset) / self.scale if self.scaled else value
        if self.dtype.startswith(("uint", "int")):
            raw = int(round(raw))
        return encode_value(raw, self.dtype, self.word_order)

    def check_range(self, value: float, what: str = "") -> None:
        """Raise ValueError (via the caller's typed error) if value is outside [min, max]."""
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError(f"{what or self.name} must be finite, got {value}")
        if self.min is not None and value < self.min:
            raise ValueError(f"{what or self.name} = {value} {self.units} is below the profile minimum {self.min}")
        if self.max is not None and value > self.max:
            raise ValueError(f"{what or self.name} = {value} {self.units} is above the profile maximum {self.max}")

    def bit_names(self, word: int) -> list[str]:
        return [name for bit, name in sorted(self.bits.items()) if word >> bit & 1]


@dataclass(frozen=True)
class Profile:
    name: str
    kind: str
    registers: dict[str, RegisterSpec]
    model: str = ""
    description: str = ""
    default_unit: int = 1
    word_order: WordOrder = WordOrder.ABCD
    sections: dict = field(default_factory=dict)
    path: str = ""

    def reg(self, name: str) -> RegisterSpec:
        try:
            return self.registers[name]
        except KeyError:
            raise ProfileError(
                f"{self.path or self.name}: no register {name!r} (profile has: {', '.join(self.registers)})"
            ) from None

    def section(self, name: str, default=None) -> dict:
        if name not in self.sections:
            if default is not None:
                return default
            raise ProfileError(f"{self.path or self.name}: missing table [{name}]")
        return self.sections[name]

    def with_word_order(self, order: WordOrder | str) -> "Profile":
        """The same profile with another default word order (registers without an explicit one follow)."""
        order = WordOrder(order)
        regs = {k: (r if r.explicit_order else replace(r, word_order=order)) for k, r in self.registers.items()}
        return replace(self, word_order=order, registers=regs)


_REG_KEYS = {"address", "type", "table", "units", "scale", "offset", "word_order", "access", "min", "max", "bits", "enum", "description"}


def _fail(path, where, reason) -> ProfileError:
    return ProfileError(f"{path}: {where}: {reason}")


def _int_keys(path, where, d) -> dict:
    if not isinstance(d, dict):
        raise _fail(path, where, "must be a table of {number = name}")
    out = {}
    for k, v in d.items():
        try:
            out[int(k)] = str(v)
        except ValueError:
            raise _fail(path, f"{where}.{k}", "keys must be integers") from None
    return out


def profile_from_dict(doc: dict, path: str = "<profile>") -> Profile:
    for key in ("kind", "registers"):
        if key not in doc:
            raise _fail(path, key, "missing key")
    try:
        default_order = WordOrder(doc.get("word_order", "ABCD"))
    except ValueError:
        raise _fail(path, "word_order", f"must be one of ABCD, CDAB, BADC, DCBA, got {doc.get('word_order')!r}") from None
    regs = {}
    for name, r in doc["registers"].items():
        where = f"[registers.{name}]"
        if not isinstance(r, dict):
            raise _fail(path, where, "must be a table")
        unknown = sorted(set(r) - _REG_KEYS)
        if unknown:
            raise _fail(path, f"{where} {unknown[0]}", f"unknown key (known: {', '.join(sorted(_REG_KEYS))})")
        if "address" not in r:
            raise _fail(path, f"{where} address", "missing key")
        addr = r["address"]
        if isinstance(addr, bool) or not isinstance(addr, int) or not 0 <= addr <= 0xFFFF:
            raise _fail(path, f"{where} address", f"must be an integer 0..65535, got {addr!r}")
        dtype = r.get("type", "uint16")
        if dtype not in DATA_TYPES:
            raise _fail(path, f"{where} type", f"must be one of {', '.join(DATA_TYPES)}, got {dtype!r}")
        table = r.get("table", "holding")
        if table not in ("holding", "input"):
            raise _fail(path, f"{where} table", f"must be 'holding' or 'input', got {table!r}")
        access = r.get("access", "r")
        if access not in ("r", "rw", "w"):
            raise _fail(path, f"{where} access", f"must be r, rw or w, got {access!r}")
        try:
            order = WordOrder(r.get("word_order", default_order))
        except ValueError:
            raise _fail(path, f"{where} word_order", f"must be ABCD, CDAB, BADC or DCBA, got {r['word_order']!r}") from None
        for k in ("scale", "offset", "min", "max"):
            if k in r and (isinstance(r[k], bool) or not isinstance(r[k], (int, float))):
                raise _fail(path, f"{where} {k}", f"must be a number, got {r[k]!r}")
        if r.get("scale", 1.0) == 0:
            raise _fail(path, f"{where} scale", "must not be zero")
        regs[name] = RegisterSpec(
            name=name, address=addr, dtype=dtype, table=table, units=str(r.get("units", "")),
            scale=float(r.get("scale", 1.0)), offset=float(r.get("offset", 0.0)), word_order=order,
            access=access, min=None if "min" not in r else float(r["min"]),
            max=None if "max" not in r else float(r["max"]),
            bits=_int_keys(path, f"{where} bits", r.get("bits", {})),
            enum=_int_keys(path, f"{where} enum", r.get("enum", {})),
            explicit_order="word_order" in r,
        )
    unit = doc.get("default_unit", 1)
    if isinstance(unit, bool) or not isinstance(unit, int) or not 0 <= unit <= 247:
        raise _fail(path, "default_unit", f"must be an integer 0..247, got {unit!r}")
    sections = {k: v for k, v in doc.items() if isinstance(v, dict) and k != "registers"}
    return Profile(
        name=str(doc.get("name", Path(path).stem)), kind=str(doc["kind"]), registers=regs,
        model=str(doc.get("model", "")), description=str(doc.get("description", "")), default_unit=unit,
        word_order=default_order, sections=sections, path=str(path),
    )


def load_profile(name_or_path: str | os.PathLike | Profile) -> Profile:
    """A profile by short name (``configs/devices/<name>.toml``) or by path."""
    if isinstance(name_or_path, Profile):
        return name_or_path
    p = Path(name_or_path)
    if not (p.suffix == ".toml" or p.exists() or len(p.parts) > 1):
        p = devices_dir() / f"{name_or_path}.toml"
        if not p.exists():
            known = sorted(f.stem for f in devices_dir().glob("*.toml"))
            raise ProfileError(f"{name_or_path}: no such device profile (built-in: {', '.join(known) or 'none'})")
    try:
        path, doc = read_toml(p)
    except ConfigError as exc:
        raise ProfileError(str(exc)) from None
    return profile_from_dict(doc, str(path))
