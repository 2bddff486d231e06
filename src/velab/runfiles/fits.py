"""Fit results in a run file: one NXprocess per fit under ``/entry/fits``.

A fit is stored from its plain-data form (``result.to_dict()``), whatever
fields the fitter puts there: numbers and strings become datasets, dicts
NXcollection groups, lists of numbers or strings 1-D datasets, lists of
records (the Kelvin-Voigt elements) a group of columns, each model of
``models`` an NXcollection named after it. Reading back is tolerant: fields
the reader does not know are kept in the dict and ignored by the result
classes; fields missing from an older file take their defaults.

:func:`save_fit` is the one way a fit gets into a run (``velab fit``, the GUI
archive's re-fit, the recorder's online fit): atomic (:mod:`velab.runfiles.atomic`),
and it can only add or replace a group under ``/entry/fits``.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import re

import h5py
import numpy as np

from velab.version import __version__
from velab.errors import DataError
from velab.runfiles import layout as L
from velab.runfiles.atomic import edit_copy, stage

FIT_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.+-]{0,63}")
_UNITS = {"window": "s", "window_s": "s", "window_s_requested": "s", "sample_rate_hz": "Hz", "duration_s": "s",
          "F": "m2", "rss": "m2", "wave_speed": "m/s", "E": "Pa", "eta": "Pa.s", "tau": "s", "J": "Pa-1",
          "n": "1", "k": "1", "m": "1", "evaluations": "1", "jacobians": "1", "starts": "1", "aic": "1",
          "aicc": "1", "bic": "1", "delta_aic": "1", "weight": "1", "lag1_autocorr": "1"}
_SUFFIX_UNITS = (("_m_s", "m/s"), ("_pa_s", "Pa.s"), ("_per_pa", "Pa-1"), ("_pa", "Pa"), ("_hz", "Hz"),
                 ("_s", "s"), ("_m", "m"))


def validate_fit_name(name: str) -> str:
    """A fit name is a plain name: letters, digits, ``_ . + -``, up to 64, starting with a letter or digit."""
    if not isinstance(name, str) or not FIT_NAME.fullmatch(name):
        raise DataError(f"fit name {name!r} is not allowed: use 1-64 letters, digits, '_', '.', '+' or '-', "
                        "starting with a letter or digit (fits are stored under /entry/fits/NAME only)")
    return name


def default_fit_name(result) -> str:
    """A name that changes with the settings that change the result: method, window, reduced."""
    d = _as_dict(result)
    window = d.get("window", d.get("window_s", float("nan")))
    name = f"{d.get('method', 'fit')}_w{float(window):g}s" + ("_reduced" if (d.get("settings") or {}).get("reduced") else "")
    return re.sub(r"[^A-Za-z0-9_.+-]", "_", name)[:64]


def _as_dict(result) -> dict:
    return result.to_dict() if hasattr(result, "to_dict") else dict(result)


def _units_of(key: str) -> str | None:
    if key in _UNITS:
        return _UNITS[key]
    if key.startswith("wave_speed"):
        return "m/s"
    for suffix, units in _SUFFIX_UNITS:
        if key.endswith(suffix):
            return units
    return None


def _is_number(v) -> bool:
    return isinstance(v, (bool, int, float, np.integer, np.floating, np.bool_))


def _write_value(g: h5py.Group, key: str, value) -> None:
    if isinstance(value, dict):
        sub = g.create_group(key)
        sub.attrs["NX_class"] = "NXcollection"
        for k, v in value.items():
            _write_value(sub, str(k).replace("/", "_"), v)
        return
    if isinstance(value, (list, tuple)) and value and all(isinstance(v, dict) for v in value) \
            and all(v.keys() == value[0].keys() for v in value) \
            and all(_is_number(x) for v in value for x in v.values()):
        sub = g.create_group(key)  # records with the same numeric fields: one column each
        sub.attrs["NX_class"] = "NXcollection"
        sub.attrs["velab_records"] = len(value)
        for k in value[0]:
            _write_value(sub, str(k), [v[k] for v in value])
        return
    if isinstance(value, (list, tuple, np.ndarray)):
        seq = list(np.asarray(value).tolist()) if isinstance(value, np.ndarray) else list(value)
        if all(_is_number(v) for v in seq):
            ds = g.create_dataset(key, data=np.asarray(seq, dtype=float if any(isinstance(v, float) for v in seq) else None)
                                  if seq else np.zeros(0))
        elif all(isinstance(v, str) for v in seq):
            ds = g.create_dataset(key, data=seq, dtype=L.VLEN_STR)
        else:
            L.write_json(g, key, seq)
            return
        ds.attrs["velab_list"] = True
    elif value is None:
        L.write_json(g, key, None)
        return
    elif isinstance(value, str):
        ds = L.write_str(g, key, value)
        return
    elif _is_number(value):
        ds = g.create_dataset(key, data=value)
    else:
        L.write_json(g, key, value)
        return
    units = _units_of(key)
    if units is not None and ds.dtype.kind in "fiu":
        ds.attrs["units"] = units


def _read_value(obj):
    if isinstance(obj, h5py.Group):
        if "velab_records" in obj.attrs:
            n = int(obj.attrs["velab_records"])
            cols = {k: _read_value(v) for k, v in obj.items()}
            return [{k: (c[i] if isinstance(c, list) and i < len(c) else None) for k, c in cols.items()} for i in range(n)]
        return {k: _read_value(v) for k, v in obj.items()}
    if obj.attrs.get("mime_type", "") == "application/json":
        return json.loads(L.to_str(obj[()]))
    v = obj[()]
    if obj.dtype.kind in "SOU" or h5py.check_string_dtype(obj.dtype) is not None:
        return [L.to_str(x) for x in np.atleast_1d(v)] if obj.ndim else L.to_str(v)
    if obj.ndim:
        return np.asarray(v).tolist()
    v = v.item() if hasattr(v, "item") else v
    return v


def write_fit_group(parent: h5py.Group, name: str, result, kind: str | None = None) -> h5py.Group:
    """Write ``result`` (a SweepResult or its ``to_dict()``) as the NXprocess ``parent/name``; ``kind``
    (e.g. "joint": a fit over several runs, velab.fitting.joint) goes into the attribute ``velab_fit_kind``."""
    validate_fit_name(name)
    d = _as_dict(result)
    if name in parent:
        del parent[name]
    g = parent.create_group(name)
    stage("writing")
    g.attrs["NX_class"] = "NXprocess"
    if kind:
        g.attrs["velab_fit_kind"] = kind
    L.write_str(g, "program", "velab")
    L.write_str(g, "version", __version__)
    L.write_str(g, "date", _dt.datetime.now(_dt.timezone.utc).astimezone().isoformat(timespec="seconds"))
    for key, value in d.items():
        if key == "models":
            continue
        _write_value(g, "velab_" + key if key in ("program", "version", "date") else key, value)
    for i, model in enumerate(d.get("models", [])):
        mname = str(model.get("name", f"model{i}"))
        if not FIT_NAME.fullmatch(mname) or mname in g:
            mname = f"model{i}"
        s = g.create_group(mname)
        s.attrs["NX_class"] = "NXcollection"
        s.attrs["model_index"] = i
        for key, value in model.items():
            _write_value(s, key, value)
    return g


def read_fit_dict(g: h5py.Group) -> dict:
    """The plain-data form of a stored fit (the ``to_dict()`` it was written from)."""
    if "method" in g.attrs and "method" not in g:
        return _read_legacy(g)
    d, models = {}, []
    for key, obj in g.items():
        if isinstance(obj, h5py.Group) and "model_index" in obj.attrs:
            models.append((int(obj.attrs["model_index"]), _read_value(obj)))
        elif key not in ("program", "version", "date"):
            d[key[6:] if key.startswith("velab_") and key[6:] in ("program", "version", "date") else key] = _read_value(obj)
    d["models"] = [m for _, m in sorted(models, key=lambda im: im[0])]
    d["date"] = L.read_str(g, "date")
    if "velab_fit_kind" in g.attrs:
        d["fit_kind"] = L.to_str(g.attrs["velab_fit_kind"])
    return d


def _read_legacy(g: h5py.Group) -> dict:
    """Format 1.0: everything in attributes, elements as datasets."""
    a = g.attrs
    models = []
    for mname, s in g.items():
        if not isinstance(s, h5py.Group):
            continue
        m = {k: (v.item() if hasattr(v, "item") else L.to_str(v)) for k, v in s.attrs.items() if k != "NX_class"}
        m["name"] = mname
        m["wave_speed"] = m.pop("wave_speed_m_s", math.nan)
        E, eta = s["E_pa"][()], s["eta_pa_s"][()]
        m["elements"] = [{"E": float(e), "eta": float(h), "tau": float(h / e), "J": float(1 / e)} for e, h in zip(E, eta)]
        models.append(m)
    models.sort(key=lambda m: (bool(m.get("reduced")), int(m.get("m", 0))))
    return {"n": int(a["n"]), "window": float(a["window_s"]), "sample_rate_hz": float(a.get("sample_rate_hz", np.nan)),
            "method": L.to_str(a["method"]), "settings": json.loads(L.to_str(a.get("settings", "{}"))),
            "best": L.to_str(a.get("best_model", "")), "date": L.to_str(a.get("date", "")), "models": models}


def sweep_from_dict(d: dict):
    """A SweepResult from its ``to_dict()`` form (as stored), tolerant of missing and extra fields."""
    from velab.fitting.results import SweepResult  # lazy: the fitting package (scipy) is heavy for `velab info`

    return SweepResult.from_dict(d)


def read_fit_group(g: h5py.Group):
    """The stored fit ``g`` as a SweepResult."""
    return sweep_from_dict(read_fit_dict(g))


def save_fit(path: str | os.PathLike, result, name: str | None = None, *, kind: str | None = None) -> str:
    """Add (or replace) the fit ``name`` in the run at ``path``, atomically; returns the name.
    ``kind``: stored as the group's ``velab_fit_kind`` attribute ("joint" for a fit over several runs).

    Only ``/entry/fits/<name>`` changes; the recorded data stay bit-identical.
    Raises RunStillOpen for a run still flagged open for writing, DataError
    for a bad name or a file that cannot be saved into.
    """
    name = validate_fit_name(name or default_fit_name(result))
    with edit_copy(path) as fh:
        e = fh["entry"]
        if "fits" not in e:
            g = e.create_group("fits")
            g.attrs["NX_class"] = "NXcollection"
        write_fit_group(e["fits"], name, result, kind)
    return name
