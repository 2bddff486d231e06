"""Reading run files: :func:`read_run` (all of a run in memory) and :func:`open_run_file`.

Any file, however damaged, gives either a :class:`Run` or one line of
:class:`~velab.errors.DataError` within seconds: no traceback, no hang.
"""

from __future__ import annotations

import contextlib
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import h5py
import numpy as np

from velab import bounds
from velab.config import Material, material_from_dict
from velab.fitting.window import enough_samples, steady_head, window_slice
from velab.rig import Manoeuvre, Rig, checked_rig, rig_from_dict
from velab.errors import DataError, VelabError
from velab.runfiles import layout as L
from velab.runfiles import soundness
from velab.runfiles import superblock as sb_
from velab.runfiles.h5open import RunStillOpen, open_h5

__all__ = ["Run", "RunStillOpen", "open_run_file", "read_run"]


@dataclass
class Run:
    """A run read back from its file (all arrays in memory)."""

    path: Path
    title: str
    status: str  # as stored; "recording" for a run whose writer never closed it
    status_reason: str
    start_time: str
    end_time: str
    time_s: np.ndarray  # s from the trigger
    head_m: np.ndarray  # absolute pressure head at the transducer
    sample_rate_hz: float
    rig: Rig  # with the run's own manoeuvre (/entry/manoeuvre)
    trigger_time_s: float = 0.0
    material: Material | None = None  # the truth, for synthetic runs
    noise_std_m: float | None = None
    channels: dict[str, np.ndarray] = field(default_factory=dict)  # other fast channels by name
    channel_units: dict[str, str] = field(default_factory=dict)
    events: list[tuple[float, str, str]] = field(default_factory=list)
    gaps: list[tuple[int, int]] = field(default_factory=list)  # (sample index, samples lost)
    fit_names: list[str] = field(default_factory=list)
    format_version: str = L.FORMAT_VERSION
    velab_version: str = ""
    source: dict = field(default_factory=dict)  # how the run was made (synth options, CSV file, bench)
    manoeuvre: dict = field(default_factory=dict)  # every value of /entry/manoeuvre
    settings: dict = field(default_factory=dict)
    versions: dict = field(default_factory=dict)  # velab and library versions that wrote the run
    file_name: str = ""
    open_for_write: bool = False  # flagged open by a writer (live, or killed)
    # what is wrong with the run's structure (velab.runfiles.soundness), "" for a sound run: a damaged run
    # is shown, never written into
    damage: str = ""

    @property
    def sound(self) -> bool:
        return not self.damage

    @property
    def incomplete(self) -> bool:
        """True for a run whose writer never closed it (crash, kill, power loss)."""
        return self.status == "recording"

    @property
    def n_samples(self) -> int:
        return int(self.time_s.size)

    @property
    def duration_after_trigger_s(self) -> float:
        if self.time_s.size == 0:
            return 0.0
        return float(self.time_s[-1] - self.trigger_time_s) + 1.0 / self.sample_rate_hz

    @property
    def steady_head_m(self) -> float:
        """The fit path's steady head (velab.fitting.window): the baseline's mean, or the rig's."""
        return steady_head(self.time_s, self.head_m, self.trigger_time_s, self.rig.steady_head_m, self.sample_rate_hz)

    def head_perturbation(self) -> np.ndarray:
        """Head minus the steady pre-trigger head (what the model predicts)."""
        return self.head_m - self.steady_head_m

    def fit_window(self, window_s: float | None) -> tuple[np.ndarray, np.ndarray]:
        """Time (s from the trigger) and head perturbation over ``window_s`` after the trigger.

        ``None`` takes everything after the trigger. Raises DataError for a window
        longer than the record, a gap in it, or NaN.
        """
        avail = self.duration_after_trigger_s
        if window_s is None:
            window_s = avail
        if not window_s > 0:
            raise DataError(f"{self.path}: fit window must be positive, got {window_s} s")
        if window_s > avail + 0.5 / self.sample_rate_hz:
            raise DataError(
                f"{self.path}: fit window {window_s:g} s is longer than the record after the trigger ({avail:.3f} s)"
            )
        inside = window_slice(self.time_s, self.trigger_time_s, window_s, self.sample_rate_hz)
        t = self.time_s[inside] - self.trigger_time_s
        h = self.head_m[inside] - self.steady_head_m
        if not enough_samples(t.size):
            raise DataError(f"{self.path}: only {t.size} samples in the fit window")
        bad = ~np.isfinite(h)
        if bad.any():
            i = int(np.argmax(bad))
            raise DataError(f"{self.path}: head is NaN at t = {t[i]:.4f} s in the fit window ({int(bad.sum())} samples)")
        first = inside.start
        for idx, lost in self.gaps:
            if first < idx < first + t.size and lost > 0:
                raise DataError(
                    f"{self.path}: {lost} samples lost before t = {self.time_s[idx] - self.trigger_time_s:.4f} s, "
                    "inside the fit window (shorten the window)"
                )
        dt = np.diff(t)
        if dt.size and np.abs(dt - 1.0 / self.sample_rate_hz).max() > 1e-3 / self.sample_rate_hz + 1e-9:
            raise DataError(f"{self.path}: time axis is not uniform in the fit window")
        return t, h


def _damaged(path: Path, exc: BaseException) -> DataError:
    msg = str(exc).split("\n")[0].strip()
    return DataError(f"{path}: damaged velab run file ({type(exc).__name__}{': ' + msg if msg else ''})")


@contextlib.contextmanager
def open_run_file(path: str | os.PathLike) -> Iterator[h5py.File]:
    """Open a velab run file read-only; every failure is a one-line DataError.

    Runs are never opened for writing in place: fits are saved by
    :func:`velab.runfiles.save_fit` (copy and rename).
    """
    path = Path(path)
    with open_h5(path) as fh:
        try:
            fmt = L.to_str(fh.attrs.get("file_format", ""))
            has_entry = "entry" in fh and isinstance(fh["entry"], h5py.Group)
        except Exception as exc:  # noqa: BLE001 - h5py raises many types on a damaged file
            raise _damaged(path, exc) from None
        if fmt != L.FILE_FORMAT or not has_entry:
            raise DataError(f"{path}: not a velab run file (no /entry with file_format={L.FILE_FORMAT})")
        version = L.to_str(fh.attrs.get("format_version", "1.0"))
        try:
            major = int(version.split(".")[0])
        except ValueError:
            raise DataError(f"{path}: damaged velab run file (format_version {version!r})") from None
        if major not in L.READABLE_MAJORS:
            raise DataError(f"{path}: run file format {version} is not one this velab reads "
                            f"({', '.join(f'{m}.x' for m in L.READABLE_MAJORS)}); update velab")
        yield fh


def read_run(path: str | os.PathLike) -> Run:
    """Read a run file into memory. Every problem is a one-line DataError."""
    path = Path(path)
    with open_run_file(path) as fh:
        try:
            return _read_entry(path, fh)
        except VelabError as exc:  # a DataError, or the ConfigError of a stored rig or material
            if str(exc).startswith(str(path)):
                raise DataError(str(exc)) from None
            raise DataError(f"{path}: damaged velab run file ({exc})") from None
        except (Exception, MemoryError) as exc:  # noqa: BLE001 - h5py and json raise many types on damage
            raise _damaged(path, exc) from None


def _vector(ds, name: str, limit: int, n: int | None = None, numeric: bool = False) -> np.ndarray:
    """A 1-d dataset's values; ``numeric``: real numbers only (no complex, compound, string or opaque type)."""
    if not isinstance(ds, h5py.Dataset) or ds.ndim != 1:
        raise DataError(f"{name} is not a one-dimensional dataset")
    if ds.shape[0] * max(ds.dtype.itemsize, 1) > limit:
        raise DataError(f"{name} claims {ds.shape[0]} values, more than the file can hold")
    if numeric and ds.dtype.kind not in "fiu":
        raise DataError(f"{name} holds {_dtype_name(ds.dtype)} values, not real numbers")
    if ds.shape[0] > bounds.MAX_SAMPLES:
        raise DataError(f"{name}: {ds.shape[0]} values, more than the {bounds.MAX_SAMPLES:,} of a record")
    return np.asarray(ds[:n] if n is not None else ds[()])


def _dtype_name(dtype) -> str:
    return {"c": "complex", "S": "string", "U": "string", "O": "string", "V": "compound or opaque", "b": "boolean",
            "M": "date", "m": "time-delta"}.get(dtype.kind, str(dtype))


def _check_heads(name: str, h: np.ndarray) -> None:
    """Heads a pipe can hold (velab.bounds.HEAD_M); NaN is a flagged sample, kept."""
    finite = h[np.isfinite(h)]
    if np.isinf(h).any():
        raise DataError(f"{name}: infinite values (at sample {int(np.argmax(np.isinf(h)))})")
    if finite.size and not (bounds.HEAD_M.contains(finite.min()) and bounds.HEAD_M.contains(finite.max())):
        worst = float(finite[np.argmax(np.abs(finite))])
        raise DataError(f"{name}: head {worst:g} m {bounds.HEAD_M(worst)}")


def _read_entry(path: Path, fh: h5py.File) -> Run:
    limit = 4 * os.path.getsize(path) + (16 << 20)  # no dataset may claim more than the file could hold
    damage = soundness.describe_defects(soundness.defects(fh))
    e = fh["entry"]
    data = e["data"]
    signal = L.to_str(data.attrs.get("signal", "head"))
    axis = L.to_str(np.atleast_1d(data.attrs.get("axes", ["time"]))[0])
    t = _vector(data[axis], f"/entry/data/{axis}", limit, numeric=True).astype(float)
    h = _vector(data[signal], f"/entry/data/{signal}", limit, numeric=True).astype(float)
    n = min(t.size, h.size)  # a killed writer may leave one dataset a flush ahead
    t, h = t[:n], h[:n]
    if not np.isfinite(t).all():
        raise DataError(f"/entry/data/{axis}: not a finite number at sample {int(np.argmax(~np.isfinite(t)))}")
    _check_heads(f"/entry/data/{signal}", h)
    rate = float(data[axis].attrs.get("sample_rate_hz", 0.0))
    if not (math.isfinite(rate) and rate > 0):
        rate = 1.0 / float(np.median(np.diff(t))) if n > 1 else 0.0
    if not (math.isfinite(rate) and rate > 0):
        raise DataError("no sample rate (time axis without @sample_rate_hz and fewer than 2 samples)")
    if not bounds.SAMPLE_RATE_HZ.contains(rate):
        raise DataError(f"/entry/data/{axis}: sample rate {rate:g} Hz {bounds.SAMPLE_RATE_HZ(rate)}")
    sample = e["sample"]
    rig = rig_from_dict(L.read_json(sample, "rig_json"))
    man = e.get("manoeuvre")
    manoeuvre = {}
    if isinstance(man, h5py.Group):
        for k, ds in man.items():
            if isinstance(ds, h5py.Dataset) and ds.shape == () and ds.dtype.kind in "fiu":
                manoeuvre[k] = float(ds[()])
    for key, bound in (("beta", bounds.BETA_PER_S), ("gamma", bounds.GAMMA)):
        if key in manoeuvre and bound(manoeuvre[key]):
            raise DataError(f"/entry/manoeuvre/{key}: {bound(manoeuvre[key])} (got {manoeuvre[key]:g})")
    if not math.isfinite(manoeuvre.get("trigger_time", 0.0)):
        raise DataError("/entry/manoeuvre/trigger_time: not a finite number")
    # the commanded manoeuvre is the run's, whatever the rig snapshot says (format 1.0 files disagreed)
    if "beta" in manoeuvre or "gamma" in manoeuvre:
        m = Manoeuvre(beta_per_s=manoeuvre.get("beta", rig.manoeuvre.beta_per_s),
                      gamma=manoeuvre.get("gamma", rig.manoeuvre.gamma))
        if m != rig.manoeuvre:
            rig = rig.with_changes(manoeuvre=m)
    rig = checked_rig(rig, "/entry/sample/rig_json")  # the rule its rig file was read with (velab.bounds)
    material = None
    mj = L.read_json(sample, "material_json")
    if mj is not None:
        material = material_from_dict(mj, f"{path}:/entry/sample")
    noise = sample.attrs.get("noise_std_m")
    channels, units = {}, {}
    if len(data) > bounds.MAX_CHANNELS + 2:
        raise DataError(f"/entry/data: {bounds.check_count(len(data), bounds.MAX_CHANNELS + 2, 'datasets')}")
    for name, ds in data.items():
        if name in (axis, signal) or not isinstance(ds, h5py.Dataset) or ds.ndim != 1:
            continue
        if ds.dtype.kind not in "fiu" and not name.startswith("head"):
            continue  # not a channel of numbers (a damaged or foreign dataset): not read
        channels[name] = _vector(ds, f"/entry/data/{name}", limit, n, numeric=True)
        if name.startswith("head"):
            _check_heads(f"/entry/data/{name}", channels[name].astype(float))
        units[name] = L.to_str(ds.attrs.get("units", ""))
    events = []
    ev = e.get("events")
    if isinstance(ev, h5py.Group) and "time" in ev:
        for tt, kind, msg in zip(_vector(ev["time"], "events/time", limit), _vector(ev["kind"], "events/kind", limit),
                                 _vector(ev["message"], "events/message", limit)):
            kind, msg = L.to_str(kind), L.to_str(msg)
            if kind == L.CONTINUED and events:  # a long message written on several fixed-size rows
                events[-1] = (events[-1][0], events[-1][1], events[-1][2] + msg)
            else:
                events.append((float(tt), kind, msg))
    gaps = []
    gp = e.get("gaps")
    if isinstance(gp, h5py.Group) and "sample_index" in gp:
        gaps = [(int(i), int(c)) for i, c in zip(_vector(gp["sample_index"], "gaps/sample_index", limit),
                                                  _vector(gp["lost"], "gaps/lost", limit))]
    notes = e.get("notes")
    source = L.read_json(notes, "source_json", {}) if isinstance(notes, h5py.Group) else {}
    settings = L.read_json(notes, "settings_json", {}) if isinstance(notes, h5py.Group) else {}
    versions = L.read_json(notes, "versions_json", {}) if isinstance(notes, h5py.Group) else {}
    fits = e.get("fits")
    return Run(
        path=path,
        title=L.read_str(e, "title"),
        status=L.read_str(e, "status", "recording"),
        status_reason=L.read_str(e, "status_reason"),
        start_time=L.read_str(e, "start_time"),
        end_time=L.read_str(e, "end_time"),
        time_s=t,
        head_m=h,
        sample_rate_hz=rate,
        rig=rig,
        trigger_time_s=float(manoeuvre.get("trigger_time", 0.0)),
        material=material,
        noise_std_m=None if noise is None or (isinstance(noise, float) and math.isnan(noise)) else float(noise),
        channels=channels,
        channel_units=units,
        events=events,
        gaps=gaps,
        fit_names=sorted(k for k, g in fits.items() if isinstance(g, h5py.Group)) if isinstance(fits, h5py.Group) else [],
        format_version=L.to_str(fh.attrs.get("format_version", "")),
        velab_version=L.to_str(fh.attrs.get("creator_version", "")),
        source=source if isinstance(source, dict) else {},
        manoeuvre=manoeuvre,
        settings=settings if isinstance(settings, dict) else {},
        versions=versions if isinstance(versions, dict) else {},
        file_name=L.to_str(fh.attrs.get("file_name", "")),
        open_for_write=sb_.read_superblock(path).open_for_write,
        damage=damage,
    )
