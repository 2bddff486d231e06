"""Is a run file sound: the structure every velab run has, checked on open (docs/run-format.md).

A run whose structure is damaged (its status deleted or not one of the statuses, its format
version, a NeXus class or the NXdata signal removed, its manoeuvre or rig gone) may still be
readable, and ``velab info`` shows what is left, naming it damaged; but nothing is ever
written into it: :func:`velab.runfiles.save_fit` refuses it (``velab fit --no-save`` may still
fit it). :func:`defects` lists what is wrong, in words, on an open ``h5py.File``.
"""

from __future__ import annotations

import h5py

from velab.runfiles import layout as L

# (path, NeXus class) every run has; data's @signal names its head dataset
NX_CLASSES = (("/", "NXroot"), ("entry", "NXentry"), ("entry/data", "NXdata"))


def _attr(obj, name: str) -> str | None:
    if name not in obj.attrs:
        return None
    try:
        return L.to_str(obj.attrs[name])
    except Exception:  # noqa: BLE001 - a retyped attribute: what it holds is not text
        return ""


def defects(fh: h5py.File) -> list[str]:
    """What is wrong with the structure of the run ``fh`` (empty for a sound run), each a short phrase."""
    out = []
    version = _attr(fh, "format_version")
    if version is None:
        out.append("no @format_version")
    if "entry" not in fh or not isinstance(fh["entry"], h5py.Group):
        return out + ["no /entry group"]
    e = fh["entry"]
    for path, nx in NX_CLASSES:
        obj = fh[path] if path == "/" or path in fh else None
        if obj is None:
            out.append(f"no /{path}")
            continue
        got = _attr(obj, "NX_class")
        if got is None:
            out.append(f"no @NX_class on {'/' if path == '/' else '/' + path}")
        elif got != nx:
            out.append(f"@NX_class of {'/' if path == '/' else '/' + path} is {got!r}, not {nx}")
    data = e.get("data")
    if isinstance(data, h5py.Group):
        signal = _attr(data, "signal")
        if signal is None:
            out.append("no @signal on /entry/data")
        elif signal not in data or not isinstance(data[signal], h5py.Dataset):
            out.append(f"/entry/data @signal names {signal!r}, which is not a dataset there")
    status = e.get("status")
    if not isinstance(status, h5py.Dataset):
        out.append("no /entry/status")
    else:
        try:
            value = L.to_str(status[()])
        except Exception:  # noqa: BLE001 - a retyped dataset
            value = None
        if value not in L.STATUSES:
            shown = "not text" if value is None else repr(value[:40])
            out.append(f"/entry/status is {shown}, not one of {', '.join(L.STATUSES)}")
    if not isinstance(e.get("manoeuvre"), h5py.Group):
        out.append("no /entry/manoeuvre")
    sample = e.get("sample")
    if not isinstance(sample, h5py.Group):
        out.append("no /entry/sample")
    elif "rig_json" not in sample and "rig_json" not in sample.attrs:
        out.append("no rig (/entry/sample/rig_json)")
    return out


def describe_defects(found: list[str]) -> str:
    """One phrase for a list of defects: the first ones, and how many more."""
    if not found:
        return ""
    shown = "; ".join(found[:3])
    return shown + (f"; and {len(found) - 3} more" if len(found) > 3 else "")
