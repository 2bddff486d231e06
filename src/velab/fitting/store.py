"""Writing and reading fit results in a run file (``/entry/fits/<fit_name>``, docs/fitting.md).

Only the ``/entry/fits`` group is ever opened for writing (through
:func:`velab.runfile.fits_group`); a fit group of the same name is replaced, others
are left alone.
"""

from __future__ import annotations

import datetime as _dt
import json
import re

import h5py
import numpy as np

from velab.version import __version__
from velab.fitting.results import ModelFit, SweepResult

_UNITS = {"E_pa": "Pa", "eta_pa_s": "Pa s", "tau_s": "s", "J_per_pa": "1/Pa"}


def default_fit_name(result: SweepResult) -> str:
    """A name that changes with the settings that change the result: method, window, reduced."""
    name = f"{result.method}_w{result.window_s:g}s" + ("_reduced" if result.settings.get("reduced") else "")
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name)


def write_fit_group(parent: h5py.Group, name: str, result: SweepResult) -> h5py.Group:
    """Write ``result`` as ``parent/name`` (replacing a group of that name)."""
    if name in parent:
        del parent[name]
    g = parent.create_group(name)
    g.attrs["NX_class"] = "NXprocess"
    g.attrs["program"] = "velab"
    g.attrs["version"] = __version__
    g.attrs["method"] = result.method
    g.attrs["window_s"] = float(result.window_s)
    g.attrs["n"] = int(result.n)
    g.attrs["best_model"] = result.best.name
    g.attrs["date"] = _dt.datetime.now(_dt.timezone.utc).astimezone().isoformat(timespec="seconds")
    g.attrs["settings"] = json.dumps(result.settings)
    g.attrs["sample_rate_hz"] = float(result.sample_rate_hz)
    for f in result.models:
        s = g.create_group(f.name)
        s.attrs["NX_class"] = "NXparameters"
        for key in ("m", "k"):
            s.attrs[key] = int(getattr(f, key))
        for key in ("F", "aic", "aicc", "bic", "delta_aic", "weight", "wave_speed_m_s", "lag1_autocorr"):
            s.attrs[key] = float(getattr(f, key))
        s.attrs["support"] = f.support
        s.attrs["reduced"] = bool(f.reduced)
        for key, values in (("E_pa", f.E_pa), ("eta_pa_s", f.eta_pa_s), ("tau_s", f.tau_s), ("J_per_pa", f.J_per_pa)):
            ds = s.create_dataset(key, data=np.asarray(values, dtype=float).reshape(-1))
            ds.attrs["units"] = _UNITS[key]
    return g


def save_fit(path, result: SweepResult, name: str | None = None) -> str:
    """Add (or replace) the fit group in the run file at ``path``; returns its name."""
    from velab.runfile import fits_group

    name = name or default_fit_name(result)
    with fits_group(path) as parent:
        write_fit_group(parent, name, result)
    return name


def read_fit_group(g: h5py.Group) -> SweepResult:
    """Inverse of :func:`write_fit_group` (parameters and statistics, not evaluation counts)."""
    models = []
    for name, s in g.items():
        if not isinstance(s, h5py.Group):
            continue
        a = s.attrs
        f = ModelFit(
            name=name, m=int(a["m"]), k=int(a["k"]), reduced=bool(a["reduced"]), n=int(g.attrs["n"]),
            F=float(a["F"]), wave_speed_m_s=float(a["wave_speed_m_s"]),
            E_pa=tuple(float(v) for v in s["E_pa"][()]), eta_pa_s=tuple(float(v) for v in s["eta_pa_s"][()]),
            lag1_autocorr=float(a["lag1_autocorr"]),
        )
        for key in ("aic", "aicc", "bic", "delta_aic", "weight"):
            setattr(f, key, float(a[key]))
        f.support = str(a["support"])
        models.append(f)
    models.sort(key=lambda f: (f.reduced, f.m))
    return SweepResult(
        n=int(g.attrs["n"]), window_s=float(g.attrs["window_s"]),
        sample_rate_hz=float(g.attrs.get("sample_rate_hz", np.nan)), method=str(g.attrs["method"]),
        settings=json.loads(g.attrs.get("settings", "{}")), models=models,
    )
