"""Reading and checking TOML configuration files: one machinery for every kind.

Rigs, materials, benches, device profiles and simulator configs are all read
here, by the application (:mod:`velab.config`) and by the device layer
(``velab.drivers``, ``velab.simulators``) alike. It is a leaf module (standard
library and :mod:`velab.errors` only), so the device layer never imports the
application.

Every error is one line, ``FILE: WHERE KEY: reason``, raised as the caller's
error class (``ConfigError`` by default; drivers pass their ``ProfileError``).

    r = Reader(path, doc)
    pipe = r.read(r.table("pipe"), "[pipe] ", {"length_m": Key(float, check=positive)})
    rate = r.get(acq, "acquisition.", "rate_hz", float, check=within(1.0, 1e5))
"""

from __future__ import annotations

import math
import os
import tomllib
from dataclasses import dataclass
from typing import Any, Callable

from velab.errors import ConfigError, one_line
from velab.inputfiles import check_input_file

# Configs are hand-written text of a few kB; anything past this is not one (or is
# /dev/zero): refuse it before reading rather than parse without bound.
MAX_CONFIG_BYTES = 1 << 20

REQUIRED = object()

# Every number in a config is a hand-written engineering value: finite, and 0 or of magnitude
# between these. Beyond them, products and powers of several keys under/overflow (a rig with a
# 1e-300 m pipe), which is never a real configuration.
MAGNITUDE_RANGE = (1e-30, 1e30)


def read_toml(path, *, error: type[Exception] = ConfigError, max_bytes: int = MAX_CONFIG_BYTES):
    """Parse one TOML file -> ``(path, doc)``; anything wrong is one ``error`` naming the file.

    ``path`` is a filesystem path or an ``importlib.resources`` Traversable (built-in
    configs). Only regular files below ``max_bytes`` are read: a FIFO, a device or a
    directory is refused before it is opened.
    """
    if isinstance(path, (str, os.PathLike)):
        check_input_file(path, "TOML file", max_bytes, error)
    try:
        fh = open(path, "rb") if isinstance(path, (str, os.PathLike)) else path.open("rb")
        with fh:
            data = fh.read(max_bytes + 1)
    except FileNotFoundError:
        raise error(f"{path}: no such file") from None
    except OSError as exc:
        raise error(f"{path}: cannot read: {exc.strerror or exc}") from None
    if len(data) > max_bytes:
        raise error(f"{path}: too large for a configuration file (limit {max_bytes} bytes)")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise error(f"{path}: not a text (UTF-8) file") from None
    try:
        return path, tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{path}: invalid TOML: {exc}") from None
    except RecursionError:  # pathologically nested arrays/tables
        raise error(f"{path}: invalid TOML: nested too deeply") from None


# ------------------------------------------------------------------ value checks
# Each returns None when the value is fine, else the reason (completed with "(got V)").


def positive(v) -> str | None:
    return None if v > 0 else "must be positive"


def non_negative(v) -> str | None:
    return None if v >= 0 else "must not be negative"


def within(lo: float, hi: float, units: str = "") -> Callable[[Any], str | None]:
    """Closed interval [lo, hi]."""
    u = f" {units}" if units else ""

    def check(v) -> str | None:
        return None if lo <= v <= hi else f"must be in [{lo:g}, {hi:g}]{u}"

    return check


def above(lo: float, hi: float, units: str = "") -> Callable[[Any], str | None]:
    """Half-open interval (lo, hi]."""
    u = f" {units}" if units else ""

    def check(v) -> str | None:
        return None if lo < v <= hi else f"must be in ({lo:g}, {hi:g}]{u}"

    return check


@dataclass(frozen=True)
class Key:
    """One key of a table: its type, whether it is required, its default and its domain."""

    kind: type
    required: bool = True
    default: Any = None
    check: Callable[[Any], str | None] | None = None
    choices: tuple | None = None


_TYPE_NAMES = {float: "a number", int: "an integer", str: "a string", bool: "true or false",
               list: "an array", dict: "a table"}


class Reader:
    """Reads one parsed TOML document; every failure names file, table and key."""

    def __init__(self, path, doc: dict | None = None, error: type[Exception] = ConfigError):
        self.path = path
        self.doc = doc if doc is not None else {}
        self.error = error

    def fail(self, where: str, reason: str) -> Exception:
        where = where.strip()
        parts = [str(p) for p in (self.path, where) if p not in (None, "")]
        return self.error(one_line(": ".join(parts + [reason])))

    def table(self, name: str, required: bool = True, *, parent: dict | None = None,
              where: str | None = None, allowed=None) -> dict:
        """The sub-table ``name`` of ``parent`` (default: the document); {} if absent and optional."""
        parent = self.doc if parent is None else parent
        label = where if where is not None else f"[{name}]"
        t = parent.get(name)
        if t is None:
            if required:
                raise self.fail(label, "missing table")
            return {}
        if not isinstance(t, dict):
            raise self.fail(label, f"must be a table, got {type(t).__name__}")
        if allowed is not None:
            self.check_keys(t, label, allowed)
        return t

    def check_keys(self, table: dict, where: str, allowed) -> None:
        unknown = sorted(str(k) for k in set(table) - set(allowed))
        if unknown:
            raise self.fail(join(where, unknown[0]), f"unknown key (known: {', '.join(sorted(allowed))})")

    def read(self, table: dict, where: str, spec: dict[str, Key]) -> dict[str, Any]:
        """Every key of ``spec`` from ``table`` (defaults filled in); unknown keys are refused."""
        if not isinstance(table, dict):
            raise self.fail(where, f"must be a table, got {type(table).__name__}")
        self.check_keys(table, where, spec)
        out = {}
        for key, k in spec.items():
            label = join(where, key)
            if key not in table:
                if k.required:
                    raise self.fail(label, "missing key")
                out[key] = k.default
                continue
            out[key] = self.value(table[key], label, k)
        return out

    def get(self, table: dict, where: str, key: str, kind: type, default=REQUIRED, check=None, choices=None):
        """One key of ``table`` (labelled ``join(where, key)``); ``default`` when absent, else required."""
        label = join(where, key)
        if key not in table:
            if default is REQUIRED:
                raise self.fail(label, "missing key")
            return default
        return self.value(table[key], label, Key(kind, check=check, choices=choices))

    def value(self, v: Any, label: str, k: Key) -> Any:
        kind = k.kind
        if kind is float:
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise self.fail(label, f"must be a number, got {_show(v)}")
            try:
                v = float(v)
            except OverflowError:
                raise self.fail(label, f"must be finite, got {_show(v)}") from None
            if not math.isfinite(v):
                raise self.fail(label, f"must be finite, got {v}")
            if v != 0 and not MAGNITUDE_RANGE[0] <= abs(v) <= MAGNITUDE_RANGE[1]:
                raise self.fail(label, f"must be 0 or of magnitude {MAGNITUDE_RANGE[0]:g} .. {MAGNITUDE_RANGE[1]:g}, "
                                       f"got {v:g}")
        elif kind is bool:
            if not isinstance(v, bool):
                raise self.fail(label, f"must be true or false, got {_show(v)}")
        elif kind is int:
            if isinstance(v, bool) or not isinstance(v, int):
                raise self.fail(label, f"must be an integer, got {_show(v)}")
        elif not isinstance(v, kind):
            raise self.fail(label, f"must be {_TYPE_NAMES.get(kind, kind.__name__)}, got {_show(v)}")
        if k.choices is not None and v not in k.choices:
            raise self.fail(label, f"must be one of {', '.join(map(str, k.choices))}, got {_show(v)}")
        if k.check is not None:
            reason = k.check(v)
            if reason:
                raise self.fail(label, f"{reason} (got {_short(v)})")
        return v


def join(where: str, key: str) -> str:
    """Label of ``key`` inside ``where``: "[pipe] " + k, "[pipe]" + k -> "[pipe] k", "channels.p" + k -> "channels.p.k"."""
    if not where or where[-1] in " .":
        return f"{where}{key}"
    if where.endswith("]"):
        return f"{where} {key}"
    return f"{where}.{key}"


def _short(v) -> str:
    s = repr(v) if isinstance(v, str) else str(v)
    return s if len(s) <= 60 else s[:57] + "..."


def _show(v) -> str:
    return f"{type(v).__name__} {_short(v) if not isinstance(v, (dict, list)) else _short(repr(v))}"
