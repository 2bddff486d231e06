"""What a velab run file looks like: format version, statuses, string types, units.

One place for the names and types that the writer, the reader, the fit store
and ``velab recover`` share (docs/run-format.md describes the tree).
"""

from __future__ import annotations

import datetime as _dt
import json

import h5py
import numpy as np

FILE_FORMAT = "velab-run"
FORMAT_VERSION = "2.0"  # 2.0: fits as groups, UTF-8 strings, UDUNITS units, JSON in datasets
READABLE_MAJORS = (1, 2)
CHUNK_SAMPLES = 16384
# HDF5 bounds of every file: readable by HDF5 >= 1.10 (Debian's h5dump), which SWMR needs anyway.
LIBVER = ("v110", "v110")

STATUSES = ("recording", "completed", "completed-with-faults", "stopped", "aborted", "failed", "synthetic", "imported")

# Strings rewritten while a recording is in SWMR mode must be fixed-size (the HDF5
# library does not support variable-length data with SWMR); sizes in UTF-8 bytes.
STATUS_LEN = 32
TIME_LEN = 32
REASON_LEN = 1024
KIND_LEN = 32
MESSAGE_LEN = 1024  # a longer event message continues on rows of kind CONTINUED
CONTINUED = "+"

VLEN_STR = h5py.string_dtype("utf-8")


def fixed_str(size: int) -> np.dtype:
    return h5py.string_dtype("utf-8", size)


# Units: UDUNITS-2 strings (each checked with `udunits2`, see tests/runfiles/test_run_standards.py).
UNITS = {
    "length": "m", "time": "s", "pressure": "Pa", "viscosity": "Pa.s", "compliance": "Pa-1",
    "rate": "s-1", "flow": "m3/s", "density": "kg/m3", "kinematic_viscosity": "m2/s",
    "speed": "m/s", "percent": "%", "one": "1", "frequency": "Hz", "area": "m2", "current": "mA",
}
UDUNITS = frozenset(UNITS.values())
# Spellings of earlier velab versions and callers, mapped to their UDUNITS form.
_UNIT_ALIASES = {"": "1", "samples": "1", "counts": "1", "count": "1", "Pa s": "Pa.s", "Pa*s": "Pa.s",
                 "1/Pa": "Pa-1", "1/s": "s-1", "m^3/s": "m3/s", "kg/m^3": "kg/m3", "m^2/s": "m2/s",
                 "m^2": "m2"}


def udunits(units: str) -> str:
    """A caller's unit string in UDUNITS form ("samples" -> "1", "Pa s" -> "Pa.s")."""
    return _UNIT_ALIASES.get(units, units)


def now_iso() -> str:
    return _dt.datetime.now(_dt.timezone.utc).astimezone().isoformat(timespec="milliseconds")


def iso_of(epoch_s: float) -> str:
    return _dt.datetime.fromtimestamp(epoch_s, _dt.timezone.utc).astimezone().isoformat(timespec="milliseconds")


def to_str(v) -> str:
    """Any HDF5 string value (fixed or variable length, bytes or str, 0-d array) as str."""
    if isinstance(v, np.ndarray):
        return to_str(v[()]) if v.ndim == 0 else to_str(v.ravel()[0]) if v.size else ""
    if isinstance(v, (bytes, np.bytes_)):
        return bytes(v).decode("utf-8", "replace").rstrip("\x00").strip()
    return str(v).strip()


def encode_fixed(text: str, size: int) -> bytes:
    """UTF-8 of ``text``, cut at a character boundary to fit ``size`` bytes."""
    b = text.encode("utf-8")
    if len(b) <= size:
        return b
    return b[:size].decode("utf-8", "ignore").encode("utf-8")


def split_fixed(text: str, size: int) -> list[bytes]:
    """UTF-8 pieces of at most ``size`` bytes, never splitting a character."""
    out, b = [], text.encode("utf-8")
    while len(b) > size:
        piece = b[:size].decode("utf-8", "ignore").encode("utf-8")
        out.append(piece)
        b = b[len(piece):]
    out.append(b)
    return out


def write_str(group: h5py.Group, name: str, value: str, size: int | None = None) -> h5py.Dataset:
    """A scalar UTF-8 string dataset: variable length, or fixed ``size`` bytes if it is rewritten under SWMR."""
    if size is None:
        return group.create_dataset(name, data=value, dtype=VLEN_STR)
    return group.create_dataset(name, data=np.bytes_(encode_fixed(value, size)), dtype=fixed_str(size))


def set_str(group: h5py.Group, name: str, value: str) -> None:
    """Overwrite a scalar string dataset in place (fixed-size ones are cut to their size)."""
    ds = group[name]
    size = ds.dtype.itemsize if ds.dtype.kind == "S" else None
    ds[()] = np.bytes_(encode_fixed(value, size)) if size else value


def read_str(group: h5py.Group, name: str, default: str = "") -> str:
    if name not in group:
        return default
    obj = group[name]
    if not isinstance(obj, h5py.Dataset):
        return default
    return to_str(obj[()])


def write_json(group: h5py.Group, name: str, value) -> h5py.Dataset:
    """A JSON document as a UTF-8 string dataset (attributes are limited to 64 KiB)."""
    ds = group.create_dataset(name, data=json.dumps(value, default=str, allow_nan=True), dtype=VLEN_STR)
    ds.attrs["mime_type"] = "application/json"
    return ds


def read_json(group: h5py.Group, name: str, default=None):
    """A JSON document stored by :func:`write_json`, or as an attribute (format 1.0)."""
    if name in group and isinstance(group[name], h5py.Dataset):
        return json.loads(to_str(group[name][()]))
    if name in group.attrs:
        return json.loads(to_str(group.attrs[name]))
    return default
