"""Device profiles: register maps, data types, word order, scaling and ranges, from TOML.

A profile is ``devices/<name>.toml`` along the config search path
(:mod:`velab.configpath`: a lab's folders, ~/.config/velab, the built-in
configs) or any path::

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

from velab.configpath import config_stem, load_config
from velab.drivers.base import ProfileError
from velab.drivers.modbus_types import DATA_TYPES, WordOrder, decode_registers, encode_value, register_count
from velab.tomlschema import Key, Reader, within


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
        """Names of the set bits; a set bit the profile does not name is never hidden ("bit N")."""
        return [self.bits.get(bit, f"bit {bit}") for bit in range(word.bit_length()) if word >> bit & 1]


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


_WORD_ORDERS = tuple(o.value for o in WordOrder)
_REGISTER = {
    "address": Key(int, check=within(0, 0xFFFF)),
    "type": Key(str, False, "uint16", choices=tuple(DATA_TYPES)),
    "table": Key(str, False, "holding", choices=("holding", "input")),
    "units": Key(str, False, ""),
    "scale": Key(float, False, 1.0, check=lambda v: None if v != 0 else "must not be zero"),
    "offset": Key(float, False, 0.0),
    "word_order": Key(str, False, None, choices=_WORD_ORDERS),
    "access": Key(str, False, "r", choices=("r", "rw", "w")),
    "min": Key(float, False, None),
    "max": Key(float, False, None),
    "bits": Key(dict, False, {}),
    "enum": Key(dict, False, {}),
    "description": Key(str, False, ""),
}


def _int_keys(r: Reader, where: str, d: dict) -> dict:
    """A {number = name} table (bit fields, enums): integer keys, string names."""
    out = {}
    for k, v in d.items():
        try:
            out[int(k)] = v
        except ValueError:
            raise r.fail(f"{where}.{k}", "keys must be integers") from None
        if not isinstance(v, str):
            raise r.fail(f"{where}.{k}", f"must be a name (string), got {v!r}")
    return out


def profile_from_dict(doc: dict, path: str = "<profile>") -> Profile:
    """A typed Profile from a parsed document; every error is one ProfileError naming file and key."""
    r = Reader(path, doc, error=ProfileError)
    kind = r.get(doc, "", "kind", str)
    default_order = WordOrder(r.get(doc, "", "word_order", str, "ABCD", choices=_WORD_ORDERS))
    regs = {}
    for name, t in r.table("registers").items():
        where = f"[registers.{name}]"
        v = r.read(t, where, _REGISTER)
        if v["min"] is not None and v["max"] is not None and v["min"] > v["max"]:
            raise r.fail(f"{where} max", f"must not be below min ({v['min']})")
        regs[name] = RegisterSpec(
            name=name, address=v["address"], dtype=v["type"], table=v["table"], units=v["units"],
            scale=v["scale"], offset=v["offset"], word_order=WordOrder(v["word_order"] or default_order),
            access=v["access"], min=v["min"], max=v["max"],
            bits=_int_keys(r, f"{where} bits", v["bits"]), enum=_int_keys(r, f"{where} enum", v["enum"]),
            explicit_order=v["word_order"] is not None,
        )
    unit = r.get(doc, "", "default_unit", int, 1, check=within(0, 247))
    sections = {k: v for k, v in doc.items() if isinstance(v, dict) and k != "registers"}
    return Profile(
        name=r.get(doc, "", "name", str, config_stem(path)), kind=kind, registers=regs,
        model=r.get(doc, "", "model", str, ""), description=r.get(doc, "", "description", str, ""),
        default_unit=unit, word_order=default_order, sections=sections, path=str(path),
    )


def load_profile(name_or_path: str | os.PathLike | Profile) -> Profile:
    """A profile by short name (``devices/<name>.toml`` along the config search path) or by path."""
    if isinstance(name_or_path, Profile):
        return name_or_path
    path, doc = load_config("devices", name_or_path, error=ProfileError)
    return profile_from_dict(doc, str(path))
