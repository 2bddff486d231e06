"""Shared pieces of the property-based (hypothesis) tests: TOML text, document mutations, time limits.

The fuzz tests check three things on every generated input: no traceback (only the
input's own one-line error type escapes), no hang (each example runs under a
SIGALRM time limit), no nonsense accepted (a refused input is refused, an accepted
one is checked for sense).
"""

from __future__ import annotations

import contextlib
import json
import math
import signal
import tomllib
from pathlib import Path

from hypothesis import strategies as st


class Hang(Exception):
    """An example ran past its time limit."""


@contextlib.contextmanager
def time_limit(seconds: float):
    """Raise Hang in the main thread if the body runs longer than ``seconds``."""

    def on_alarm(signum, frame):
        raise Hang(f"no answer within {seconds} s")

    previous = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


# ------------------------------------------------------------------ TOML text


def _toml_string(s: str) -> str:
    out = []
    for ch in s:
        o = ord(ch)
        if ch == '"':
            out.append('\\"')
        elif ch == "\\":
            out.append("\\\\")
        elif o < 0x20 or o == 0x7F:
            out.append(f"\\u{o:04X}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return _toml_string(v)
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_toml_string(str(k))} = {toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(type(v))


def dumps(doc: dict) -> str:
    """A TOML document for ``doc`` (every table inline: simple, and any structure is expressible)."""
    return "".join(f"{_toml_string(str(k))} = {toml_value(v)}\n" for k, v in doc.items())


# ------------------------------------------------------------------ values and mutations

_TEXT = st.text(alphabet=st.characters(blacklist_categories=("Cs",)), max_size=12)
_NUMBERS = st.one_of(
    st.integers(min_value=-(2**63), max_value=2**63 - 1),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0, -1, 1, 0.0, -0.0, 1e-300, 1e300, 1e-30, 1e30, 5e-324, 65535, 65536, 247, 248, 2**31]),
)
SCALARS = st.one_of(_NUMBERS, st.booleans(), _TEXT,
                    st.sampled_from(["", "tcp", "rtu", "ABCD", "CDAB", "float32", "uint16", "holding", "r", "rw",
                                     "perugia", "A", "modbus_adc", "flowmeter", "valve_actuator", "streaming_adc",
                                     "25MA", "Pa", "m", "manual", "realtime", "blasius", "none", "upstream"]))
VALUES = st.recursive(SCALARS, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                       st.dictionaries(_TEXT, inner, max_size=4)), max_leaves=8)


def _paths(doc, prefix=()):
    """Every (path, value) in a nested document: dict keys and list indices."""
    yield prefix, doc
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            yield from _paths(v, prefix + (i,))


def _get(doc, path):
    for p in path:
        doc = doc[p]
    return doc


@st.composite
def mutated(draw, base: dict, max_mutations: int = 4):
    """``base`` (a valid config document) with a few random edits: values replaced by anything,
    keys deleted, keys added, tables replaced by scalars and scalars by tables."""
    doc = json.loads(json.dumps(base))  # a deep copy
    for _ in range(draw(st.integers(1, max_mutations))):
        paths = [p for p, _ in _paths(doc)]
        path = draw(st.sampled_from(paths))
        target = _get(doc, path)
        op = draw(st.sampled_from(["replace", "delete", "add", "replace"]))
        if op == "add" and isinstance(target, dict):
            key = draw(st.one_of(_TEXT, st.sampled_from(sorted({k for p in paths for k in p if isinstance(k, str)}) or ["x"])))
            target[key] = draw(VALUES)
        elif op == "add" and isinstance(target, list):
            target.append(draw(VALUES))
        elif path and op == "delete":
            parent = _get(doc, path[:-1])
            del parent[path[-1]]
        elif path:
            parent = _get(doc, path[:-1])
            parent[path[-1]] = draw(VALUES)
    return doc


def builtin_doc(kind: str, name: str) -> dict:
    from velab.configpath import find_config

    return tomllib.loads(Path(str(find_config(kind, name))).read_text())
