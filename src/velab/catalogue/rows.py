"""One run file -> one catalogue row (a flat dict of JSON values), read only.

The file is opened by :func:`velab.runfiles.open_run_file` (the same checks and
one-line errors as ``velab info``) and only its small datasets are read: no
sample array is loaded, the duration comes from the time axis's length and last
value. A file that cannot be read is a ``damaged`` row carrying the reader's
one-line reason; so is a run whose structure is not sound (:mod:`velab.runfiles.soundness`:
its status, format version, NeXus classes, signal, manoeuvre or rig gone), which ``velab info``
names damaged and ``velab fit`` will not write into: status ``damaged``, reason ``damaged run
(what is wrong)``, and what can still be read of it (title, rig, fits...) in the other fields.
An HDF5 file that is not a velab run is a row of kind ``other``.

Runs in the catalogue's worker processes (:mod:`velab.catalogue.extract`), which
give each file a deadline: a file that makes HDF5 loop is killed there.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import io
import json
import math
import os
from pathlib import Path

# the columns every row has (None where unknown), in the order of the CSV
COLUMNS = (
    "path", "kind", "status", "reason", "flags", "start_time", "end_time", "title", "operator", "specimen",
    "notes", "source", "rig", "material", "steady_flow_l_s", "measured_flow_l_s", "beta_per_s", "gamma",
    "sample_rate_hz", "n_samples", "duration_s", "fault_events", "lost_samples", "open_for_write", "n_fits",
    "fit_name", "fit_date", "best_model", "wave_speed_m_s", "wave_speed_se_m_s", "misfit", "warnings",
    "noise_ratio", "elements", "size_bytes", "mtime",
)
ROW_VERSION = 2  # bump when a row gains or changes a field: the index re-reads every file (2: unsound runs damaged)


def empty_row(path: str, kind: str, status: str, reason: str = "") -> dict:
    row = dict.fromkeys(COLUMNS)
    row.update(path=path, kind=kind, status=status, reason=reason, flags=[], n_fits=0, warnings=[], elements=[])
    return row


def _stat(row: dict, path: Path) -> None:
    try:
        st = os.stat(path)
        row["size_bytes"], row["mtime"] = st.st_size, st.st_mtime
    except OSError:
        pass


def _finite(v):
    try:
        v = float(v)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _scalar(group, name):
    import h5py

    ds = group.get(name) if group is not None else None
    if isinstance(ds, h5py.Dataset) and ds.shape == () and ds.dtype.kind in "fiu":
        return _finite(ds[()])
    return None


def _without_path(message: str, path: str) -> str:
    """The reader's one-line reason without the leading ``PATH: `` (the row has the path)."""
    return message[len(path) + 2:] if message.startswith(path + ": ") else message


def read_row(path: str | os.PathLike, walk: bool = False) -> dict:
    """The catalogue row of ``path``; never raises for a bad file (a ``damaged`` or ``other`` row).

    ``walk``: first touch every object of the file as the reader's probe does
    (:func:`velab.runfiles.h5open.walk`), so a row is ``damaged`` exactly when
    ``velab info`` would refuse the file. Off in the catalogue: it costs 5-8 x the
    row itself, and damage in what the row does not read (a data chunk) shows when
    the run is opened.
    """
    from velab.errors import DataError
    from velab.runfiles.h5open import walk as walk_file

    p = str(path)
    try:
        if walk:
            out = io.StringIO()
            with contextlib.redirect_stdout(out):
                rc = walk_file(p)
            if rc != 0:
                raise DataError(out.getvalue().strip().splitlines()[-1] if out.getvalue().strip()
                                else f"{p}: damaged HDF5 file")
        row = _read(Path(p))
    except DataError as exc:
        msg = _without_path(str(exc).split("\n")[0], p)
        row = empty_row(p, "other" if msg.startswith("not a velab run file") else "damaged",
                        "not-a-run" if msg.startswith("not a velab run file") else "damaged", msg)
    except Exception as exc:  # noqa: BLE001 - h5py and json raise many types on a damaged file
        first = str(exc).split("\n")[0].strip()
        row = empty_row(p, "damaged", "damaged",
                        f"damaged velab run file ({type(exc).__name__}{': ' + first if first else ''})")
    _stat(row, Path(p))
    return row


def _read(path: Path) -> dict:
    from velab.runfiles import soundness
    from velab.runfiles import superblock as sb_
    from velab.runfiles.reader import open_run_file

    row = empty_row(str(path), "run", "recording")
    with open_run_file(path) as fh:
        found = soundness.defects(fh)
        try:
            _fill(row, fh)
        except Exception:  # noqa: BLE001 - what is left of an unsound run may not read: its defects say why
            if not found:
                raise
    row["open_for_write"] = bool(sb_.read_superblock(path).open_for_write)
    if found:  # as velab info names it, whatever status the file still claims
        row["status"], row["reason"] = "damaged", f"damaged run ({soundness.describe_defects(found)})"
    flags = []
    if row["fault_events"] or row["status"] == "completed-with-faults":
        flags.append("faults")
    if row["lost_samples"]:
        flags.append("gaps")
    if row["open_for_write"]:
        flags.append("open")  # a recorder holds it, or died holding it
    if row["misfit"]:
        flags.append("misfit")
    row["flags"] = flags
    return row


def _fill(row: dict, fh) -> None:
    """The row's fields from the open run ``fh`` (small datasets only)."""
    import h5py

    from velab.runfiles import layout as L

    e = fh["entry"]
    row["status"] = L.read_str(e, "status", "recording") or "recording"
    row["reason"] = L.read_str(e, "status_reason")
    row["start_time"] = L.read_str(e, "start_time") or None
    row["end_time"] = L.read_str(e, "end_time") or None
    row["title"] = L.read_str(e, "title")
    notes = e.get("notes")
    if isinstance(notes, h5py.Group):
        settings = L.read_json(notes, "settings_json", {})
        source = L.read_json(notes, "source_json", {})
        if isinstance(settings, dict):  # the recorder's RecordSettings: the operator's metadata
            for k in ("operator", "specimen", "notes"):
                v = settings.get(k)
                row[k] = v if isinstance(v, str) else ""
        if isinstance(source, dict):
            row["source"] = str(source.get("kind") or "") or None
    sample = e.get("sample")
    if isinstance(sample, h5py.Group):
        rig = L.read_json(sample, "rig_json", {})
        row["rig"] = (rig.get("name") if isinstance(rig, dict) else None) or L.read_str(sample, "name") or None
        row["steady_flow_l_s"] = _scalar(sample, "steady_flow")
        mat = sample.get("material")
        if isinstance(mat, h5py.Group):
            row["material"] = L.read_str(mat, "name") or None
    man = e.get("manoeuvre")
    if isinstance(man, h5py.Group):
        row["beta_per_s"], row["gamma"] = _scalar(man, "beta"), _scalar(man, "gamma")
        q = _scalar(man, "steady_flow")
        row["steady_flow_l_s"] = q if q is not None else row["steady_flow_l_s"]
        row["measured_flow_l_s"] = _scalar(man, "measured_steady_flow")
    for k in ("steady_flow_l_s", "measured_flow_l_s"):
        row[k] = row[k] * 1e3 if row[k] is not None else None
    trigger = _scalar(man, "trigger_time") if isinstance(man, h5py.Group) else None
    _timing(row, e, trigger or 0.0)
    _faults(row, e)
    _fits(row, e)


def _timing(row: dict, e, trigger: float) -> None:
    import h5py

    from velab.runfiles import layout as L

    data = e.get("data")
    if not isinstance(data, h5py.Group):
        return
    axis = L.to_str(list(data.attrs.get("axes", ["time"]))[0] if "axes" in data.attrs else "time")
    t = data.get(axis)
    if not isinstance(t, h5py.Dataset) or t.ndim != 1:
        return
    n = int(t.shape[0])
    signal = data.get(L.to_str(data.attrs.get("signal", "head")))
    if isinstance(signal, h5py.Dataset) and signal.ndim == 1:
        n = min(n, int(signal.shape[0]))  # a killed writer may leave one dataset a flush ahead
    rate = _finite(t.attrs.get("sample_rate_hz"))
    if (rate is None or rate <= 0) and n > 1:
        dt = _finite(t[1] - t[0])
        rate = 1.0 / dt if dt and dt > 0 else None
    row["sample_rate_hz"], row["n_samples"] = rate, n
    if n and rate:
        last = _finite(t[n - 1])
        row["duration_s"] = None if last is None else max(0.0, last - trigger + 1.0 / rate)


def _faults(row: dict, e) -> None:
    import h5py

    from velab.runfiles import layout as L

    ev = e.get("events")
    if isinstance(ev, h5py.Group) and isinstance(ev.get("kind"), h5py.Dataset) and ev["kind"].ndim == 1:
        row["fault_events"] = sum(1 for k in ev["kind"][()] if L.to_str(k) == "fault")
    else:
        row["fault_events"] = 0
    gp = e.get("gaps")
    row["lost_samples"] = 0
    if isinstance(gp, h5py.Group) and isinstance(gp.get("lost"), h5py.Dataset) and gp["lost"].ndim == 1:
        row["lost_samples"] = int(sum(int(x) for x in gp["lost"][()] if x > 0))


def _fit_date(g) -> str:
    from velab.runfiles import layout as L

    return L.read_str(g, "date") or L.to_str(g.attrs.get("date", ""))  # format 1.0: in attributes


def _when(date: str) -> float:
    try:
        d = _dt.datetime.fromisoformat(date)
    except ValueError:
        return -math.inf
    return (d if d.tzinfo else d.astimezone()).timestamp()


def _fits(row: dict, e) -> None:
    """The latest fit (by its date) of the run: best model, its wave speed +- SE, warnings, elements."""
    import h5py

    fits = e.get("fits")
    groups = {k: g for k, g in fits.items() if isinstance(g, h5py.Group)} if isinstance(fits, h5py.Group) else {}
    row["n_fits"] = len(groups)
    if not groups:
        return
    dates = {k: _fit_date(g) for k, g in groups.items()}
    name = max(groups, key=lambda k: (_when(dates[k]), k))
    row["fit_name"], row["fit_date"] = name, dates[name] or None
    try:
        d = _latest_fit(groups[name])
    except Exception as exc:  # noqa: BLE001 - one damaged fit group must not hide the run
        row["warnings"] = [f"unreadable: {type(exc).__name__}"]
        return
    warnings = [w for w in (d.get("warnings") or []) if isinstance(w, dict)]  # absent in older fits
    row["warnings"] = [str(w.get("code", "")) for w in warnings]
    row["misfit"] = any(w.get("code") == "misfit" for w in warnings)
    row["best_model"] = d.get("best")
    model = d.get("model")
    if not isinstance(model, dict):
        return
    row["wave_speed_m_s"] = _finite(model.get("wave_speed"))
    row["wave_speed_se_m_s"] = _finite(model.get("wave_speed_se"))
    row["noise_ratio"] = _finite(model.get("noise_ratio"))
    els = model.get("elements") or []
    row["elements"] = [{"J_per_pa": _finite(el.get("J")), "tau_s": _finite(el.get("tau"))}
                       for el in els if isinstance(el, dict)]


_MODEL_FIELDS = ("name", "wave_speed", "wave_speed_se", "noise_ratio", "elements")


def _latest_fit(g) -> dict:
    """best, warnings and the best model's few fields of one stored fit.

    Read field by field through the fit store's own value reader: a whole fit is
    ~200 datasets (0.15 s), these are ~8.
    """
    import h5py

    from velab.runfiles.fits import _read_value, read_fit_dict

    if "method" in g.attrs and "method" not in g:  # format 1.0: attributes; small, read it whole
        d = read_fit_dict(g)
        best = str(d.get("best") or "") or None
        return {"best": best, "warnings": [], "model": next((m for m in d.get("models") or []
                                                             if m.get("name") == best), None)}
    best = _read_value(g["best"]) if isinstance(g.get("best"), h5py.Dataset) else None
    best = str(best) if best else None
    warnings = _read_value(g["warnings"]) if "warnings" in g else []
    model = None
    if best:
        cand = g.get(best)
        groups = [cand] if isinstance(cand, h5py.Group) and "model_index" in cand.attrs else \
            [m for m in g.values() if isinstance(m, h5py.Group) and "model_index" in m.attrs]
        for m in groups:
            fields = {k: _read_value(m[k]) for k in _MODEL_FIELDS if k in m and k != "elements"}
            els = m.get("elements")
            if isinstance(els, h5py.Group) and "velab_records" in els.attrs:  # columns: read two of ~12
                cols = {k: _read_value(els[k]) for k in ("J", "tau") if isinstance(els.get(k), h5py.Dataset)}
                n = int(els.attrs["velab_records"])
                fields["elements"] = [{k: (c[i] if isinstance(c, list) and i < len(c) else None)
                                       for k, c in cols.items()} for i in range(n)]
            if fields.get("name", best) == best:
                model = fields
                break
    return {"best": best, "warnings": warnings if isinstance(warnings, list) else [], "model": model}


def dumps(row: dict) -> str:
    """A row as strict JSON (non-finite numbers are null)."""
    return json.dumps(row, allow_nan=False, default=str)
