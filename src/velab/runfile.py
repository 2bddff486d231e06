"""HDF5 run files: one file per water-hammer run, in a light NeXus layout.

The layout is documented in ``docs/run-format.md``. Short form::

    /                         NXroot   @default=entry @file_format=velab-run @format_version
    /entry                    NXentry  @default=data
        title, start_time, end_time, status, status_reason   (scalar string datasets)
        program_name          "velab" @version
        data/                 NXdata   @signal=head @axes=time
            time   (s from the trigger, float64, chunked, resizable)
            head   (m, absolute pressure head at the transducer)
        instrument/           NXinstrument
            pressure_transducer/  NXsensor: raw counts, signal (mA), pressure (Pa), calibration
            valve/                NXpositioner: position (fraction open), manoeuvre
            flowmeter/            NXsensor: NXlog value/time
            device_setup          JSON snapshot of the bench / simulator configuration
        sample/               NXsample: the rig (pipe, fluid, steady flow) + material truth if synthetic
        manoeuvre/            NXcollection: beta, gamma, Q0, trigger time
        events/               NXcollection: time, kind, message (the run's event log)
        gaps/                 NXcollection: sample index and count of every gap (lost samples)
        fits/                 NXcollection: one NXprocess per calibration (velab fit)
        notes/                NXnote: settings snapshot (JSON)

Writing: :class:`RunWriter` creates every dataset up front, then switches to
SWMR so that readers (the GUI, ``velab info``) can open the file while it is
written; it appends and flushes as data arrive. End-of-run facts (end_time,
status) are pre-created fixed-size datasets, because attributes cannot be
written in SWMR mode. Recorded datasets are never rewritten afterwards: fits go
under ``/entry/fits`` only (:func:`fits_group`).
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import h5py
import numpy as np

from velab.version import __version__
from velab.config import Material, Rig, material_from_dict, rig_from_dict
from velab.errors import ConfigError, DataError

FILE_FORMAT = "velab-run"
FORMAT_VERSION = "1.0"
CHUNK_SAMPLES = 16384
STATUS_LEN = 32  # fixed-size status / time strings, overwritable in SWMR mode
REASON_LEN = 256

STATUSES = ("recording", "completed", "completed-with-faults", "stopped", "aborted", "failed", "synthetic", "imported")


def now_iso() -> str:
    return _dt.datetime.now(_dt.timezone.utc).astimezone().isoformat(timespec="milliseconds")


# ----------------------------------------------------------------------------- reading


class RunStillOpen(DataError):
    """The file is held open by a SWMR writer, or its writer died without closing it."""


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
    rig: Rig
    trigger_time_s: float = 0.0
    material: Material | None = None  # the truth, for synthetic runs
    noise_std_m: float | None = None
    channels: dict[str, np.ndarray] = field(default_factory=dict)  # other fast channels by name
    channel_units: dict[str, str] = field(default_factory=dict)
    events: list[tuple[float, str, str]] = field(default_factory=list)
    gaps: list[tuple[int, int]] = field(default_factory=list)  # (sample index, samples lost)
    fit_names: list[str] = field(default_factory=list)
    format_version: str = FORMAT_VERSION
    velab_version: str = ""
    source: dict = field(default_factory=dict)  # how the run was made (synth options, CSV file, bench)

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
        """Mean head before the trigger; the rig's steady head if there is no pre-trigger record."""
        pre = self.head_m[self.time_s < self.trigger_time_s]
        pre = pre[np.isfinite(pre)]
        if pre.size:
            return float(pre.mean())
        return self.rig.steady_head_m

    def head_perturbation(self) -> np.ndarray:
        """Head minus the steady pre-trigger head (what the model predicts)."""
        return self.head_m - self.steady_head_m

    def fit_window(self, window_s: float | None) -> tuple[np.ndarray, np.ndarray]:
        """Time (s from the trigger) and head perturbation over ``window_s`` after the trigger.

        ``None`` takes everything after the trigger. Raises DataError for a window
        longer than the record, a gap in it, or NaN.
        """
        after = self.time_s >= self.trigger_time_s - 0.5 / self.sample_rate_hz
        avail = self.duration_after_trigger_s
        if window_s is None:
            window_s = avail
        if window_s <= 0:
            raise DataError(f"{self.path}: fit window must be positive, got {window_s} s")
        if window_s > avail + 0.5 / self.sample_rate_hz:
            raise DataError(
                f"{self.path}: fit window {window_s:g} s is longer than the record after the trigger ({avail:.3f} s)"
            )
        inside = after & (self.time_s < self.trigger_time_s + window_s - 0.5 / self.sample_rate_hz)
        t = self.time_s[inside] - self.trigger_time_s
        h = self.head_perturbation()[inside]
        if t.size < 10:
            raise DataError(f"{self.path}: only {t.size} samples in the fit window")
        bad = ~np.isfinite(h)
        if bad.any():
            i = int(np.argmax(bad))
            raise DataError(f"{self.path}: head is NaN at t = {t[i]:.4f} s in the fit window ({int(bad.sum())} samples)")
        first = int(np.argmax(inside))
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


def _str(v) -> str:
    if isinstance(v, bytes):
        return v.decode("utf-8", "replace").rstrip("\x00").strip()
    if isinstance(v, np.ndarray):
        return _str(v[()])
    return str(v).strip()


def _read_scalar_str(group: h5py.Group, name: str, default: str = "") -> str:
    if name not in group:
        return default
    return _str(group[name][()])


@contextlib.contextmanager
def open_run_file(path: str | os.PathLike, mode: str = "r") -> Iterator[h5py.File]:
    """Open a velab run file, turning every failure into a one-line DataError."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such file")
    if path.is_dir():
        raise DataError(f"{path}: is a directory, expected a run file (.h5)")
    try:
        if not h5py.is_hdf5(path):
            raise DataError(f"{path}: not an HDF5 file")
    except OSError as exc:
        raise DataError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    try:
        if mode == "r":
            try:
                fh = h5py.File(path, "r")
            except OSError as exc:
                # A file a SWMR writer holds open (or left flagged when it was killed)
                # opens only as a SWMR reader. A truncated file must not: SWMR skips
                # the end-of-file check and its reads would retry forever.
                if "truncated" in str(exc):
                    raise
                fh = h5py.File(path, "r", swmr=True)
        else:
            fh = h5py.File(path, mode)
    except OSError as exc:
        msg = str(exc).split("\n")[0]
        if "already open for write" in msg:
            raise RunStillOpen(
                f"{path}: the run is still open for writing (being recorded, or its recorder was killed); "
                f"it can be read but not changed: `velab recover {path}` writes a closed copy"
            ) from None
        raise DataError(f"{path}: cannot be opened as HDF5, truncated or corrupt ({msg})") from None
    try:
        if _str(fh.attrs.get("file_format", "")) != FILE_FORMAT or "entry" not in fh:
            raise DataError(f"{path}: not a velab run file (no /entry with file_format={FILE_FORMAT})")
        yield fh
    finally:
        fh.close()


def read_run(path: str | os.PathLike) -> Run:
    """Read a run file into memory. Every problem is a one-line DataError."""
    path = Path(path)
    with open_run_file(path) as fh:
        try:
            return _read_entry(path, fh)
        except DataError:
            raise
        except (KeyError, OSError, ValueError, TypeError, json.JSONDecodeError, ConfigError) as exc:
            msg = str(exc).split("\n")[0]
            raise DataError(f"{path}: damaged velab run file ({type(exc).__name__}: {msg})") from None


def _read_entry(path: Path, fh: h5py.File) -> Run:
    e = fh["entry"]
    data = e["data"]
    signal = _str(data.attrs.get("signal", "head"))
    axis = _str(np.atleast_1d(data.attrs.get("axes", ["time"]))[0])
    t = np.asarray(data[axis][()], dtype=float)
    h = np.asarray(data[signal][()], dtype=float)
    n = min(t.size, h.size)  # a killed writer may leave one dataset a flush ahead
    t, h = t[:n], h[:n]
    rate = float(data[axis].attrs.get("sample_rate_hz", 0.0)) or (1.0 / float(np.median(np.diff(t))) if n > 1 else 0.0)
    sample = e["sample"]
    rig = rig_from_dict(json.loads(_str(sample.attrs["rig_json"])))
    material = None
    if "material_json" in sample.attrs:
        material = material_from_dict(json.loads(_str(sample.attrs["material_json"])), f"{path}:/entry/sample")
    noise = sample.attrs.get("noise_std_m")
    channels, units = {}, {}
    for name, ds in data.items():
        if name in (axis, signal) or not isinstance(ds, h5py.Dataset):
            continue
        channels[name] = np.asarray(ds[:n])
        units[name] = _str(ds.attrs.get("units", ""))
    events = []
    if "events" in e and "time" in e["events"]:
        ev = e["events"]
        for tt, kind, msg in zip(ev["time"][()], ev["kind"][()], ev["message"][()]):
            events.append((float(tt), _str(kind), _str(msg)))
    gaps = []
    if "gaps" in e and "sample_index" in e["gaps"]:
        gaps = [(int(i), int(c)) for i, c in zip(e["gaps"]["sample_index"][()], e["gaps"]["lost"][()])]
    trigger = float(e["manoeuvre"]["trigger_time"][()]) if "manoeuvre" in e and "trigger_time" in e["manoeuvre"] else 0.0
    source = {}
    if "notes" in e and "source_json" in e["notes"].attrs:
        source = json.loads(_str(e["notes"].attrs["source_json"]))
    return Run(
        path=path,
        title=_read_scalar_str(e, "title"),
        status=_read_scalar_str(e, "status", "recording"),
        status_reason=_read_scalar_str(e, "status_reason"),
        start_time=_read_scalar_str(e, "start_time"),
        end_time=_read_scalar_str(e, "end_time"),
        time_s=t,
        head_m=h,
        sample_rate_hz=rate,
        rig=rig,
        trigger_time_s=trigger,
        material=material,
        noise_std_m=None if noise is None or (isinstance(noise, float) and math.isnan(noise)) else float(noise),
        channels=channels,
        channel_units=units,
        events=events,
        gaps=gaps,
        fit_names=sorted(e["fits"].keys()) if "fits" in e else [],
        format_version=_str(fh.attrs.get("format_version", "")),
        velab_version=_str(fh.attrs.get("creator_version", "")),
        source=source,
    )


@contextlib.contextmanager
def fits_group(path: str | os.PathLike) -> Iterator[h5py.Group]:
    """The run's ``/entry/fits`` group, opened read-write; nothing else may be changed."""
    with open_run_file(path, "r+") as fh:
        e = fh["entry"]
        if "fits" not in e:
            g = e.create_group("fits")
            g.attrs["NX_class"] = "NXcollection"
        yield e["fits"]


def recover_run(src: str | os.PathLike, dst: str | os.PathLike | None = None) -> tuple[Path, int]:
    """Copy a run whose writer never closed it into a new, closed file; returns (copy, samples).

    The original is only read. HDF5 keeps a file that a killed SWMR writer held
    open flagged as "open for write" (``h5clear -s`` resets that flag in place);
    the copy is an ordinary closed file with every flushed sample, so fits can be
    saved into it. Its status stays ``recording`` (the run is still incomplete)
    with a reason saying where it came from.
    """
    src = Path(src)
    dst = Path(dst) if dst is not None else src.with_name(f"{src.stem}.recovered{src.suffix}")
    if dst.exists():
        raise DataError(f"{dst}: already exists; a run file is never overwritten")
    tmp = dst.with_name(f".{dst.name}.part")
    tmp.unlink(missing_ok=True)
    try:
        with open_run_file(src) as fin, h5py.File(tmp, "w-", libver="latest") as fout:
            src_data = fin["entry/data"]
            # a killed writer may leave one dataset a flush ahead: keep the common length
            n = min(src_data[_str(src_data.attrs.get("axes", ["time"])[0])].shape[0],
                    src_data[_str(src_data.attrs.get("signal", "head"))].shape[0])
            for k, v in fin.attrs.items():
                fout.attrs[k] = v
            fin.copy(fin["entry"], fout, "entry")
            data = fout["entry/data"]
            for name, ds in data.items():  # one sample count for every fast channel
                if isinstance(ds, h5py.Dataset) and ds.maxshape == (None,) and ds.shape[0] > n:
                    ds.resize((n,))
            if not _read_scalar_str(fout["entry"], "status_reason"):
                _set_str(fout["entry"], "status_reason", f"recovered copy of {src.name} (its recorder never closed it)", REASON_LEN)
        os.replace(tmp, dst)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return dst, n


# ----------------------------------------------------------------------------- writing


@dataclass(frozen=True)
class Channel:
    """A fast channel sampled on the run's time axis."""

    name: str
    units: str
    dtype: str = "f8"
    long_name: str = ""
    group: str = "data"  # "data" (NXdata) or an instrument subgroup path such as "instrument/pressure_transducer"


HEAD = Channel("head", "m", "f8", "pressure head at the transducer (absolute, above the transducer)")
DEFAULT_CHANNELS = (HEAD,)


def _set_str(group: h5py.Group, name: str, value: str, size: int) -> None:
    group[name][()] = np.bytes_(value.encode("utf-8")[:size])


def _sample_group(e: h5py.Group, rig: Rig, material: Material | None, noise_std_m: float | None) -> None:
    s = e.create_group("sample")
    s.attrs["NX_class"] = "NXsample"
    s.attrs["rig_json"] = json.dumps(rig.to_dict())
    s.attrs["name"] = rig.name
    p = rig.pipe
    for name, value, units in (
        ("pipe_length", p.length_m, "m"),
        ("inner_diameter", p.inner_diameter_m, "m"),
        ("wall_thickness", p.wall_thickness_m, "m"),
        ("constraint_coefficient", p.constraint_alpha, ""),
        ("pressure_rating", p.pressure_rating_pa if p.pressure_rating_pa is not None else float("nan"), "Pa"),
        ("fluid_density", rig.fluid.density_kg_m3, "kg/m^3"),
        ("fluid_kinematic_viscosity", rig.fluid.kinematic_viscosity_m2_s, "m^2/s"),
        ("steady_flow", rig.steady_flow_m3_s, "m^3/s"),
        ("reservoir_head", rig.reservoir_head_m, "m"),
        ("nominal_wave_speed", rig.nominal_wave_speed_m_s, "m/s"),
        ("transducer_full_scale", rig.transducer.full_scale_pa, "Pa"),
    ):
        d = s.create_dataset(name, data=float(value))
        d.attrs["units"] = units
    s.attrs["pipe_material"] = p.material
    if material is not None:
        s.attrs["material_json"] = json.dumps(material.to_dict())
        m = s.create_group("material")
        m.attrs["NX_class"] = "NXcollection"
        m.attrs["name"] = material.name
        m.attrs["model"] = material.model_name
        for name, values, units in (
            ("wave_speed", [material.wave_speed_m_s], "m/s"),
            ("E", [el.E_pa for el in material.elements], "Pa"),
            ("eta", [el.eta_pa_s for el in material.elements], "Pa*s"),
            ("tau", [el.tau_s for el in material.elements], "s"),
            ("J", [el.J_per_pa for el in material.elements], "1/Pa"),
        ):
            d = m.create_dataset(name, data=np.asarray(values, dtype=float))
            d.attrs["units"] = units
    s.attrs["noise_std_m"] = float("nan") if noise_std_m is None else float(noise_std_m)


class RunWriter:
    """Streams a run into its HDF5 file as it is recorded.

    All datasets are created at construction (chunked, resizable); with
    ``swmr=True`` the file then switches to SWMR mode so readers can follow it.
    ``append`` adds samples of the fast channels; ``event`` logs a time-stamped
    event; ``gap`` records lost samples (they are never interpolated);
    ``flush`` makes everything appended so far durable; ``close(status)``
    writes the end time and status.

    Not thread-safe: the recorder calls it from its writer thread only.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        rig: Rig,
        *,
        sample_rate_hz: float,
        title: str = "",
        channels: tuple[Channel, ...] = DEFAULT_CHANNELS,
        material: Material | None = None,
        noise_std_m: float | None = None,
        trigger_time_s: float = 0.0,
        manoeuvre: dict | None = None,
        device_setup: dict | None = None,
        settings: dict | None = None,
        source: dict | None = None,
        calibration: dict | None = None,
        slow_channels: tuple[Channel, ...] = (),
        swmr: bool = True,
        status: str = "recording",
        expected_samples: int | None = None,
    ):
        if sample_rate_hz <= 0:
            raise ValueError("sample_rate_hz must be positive")
        self.path = Path(path)
        self.sample_rate_hz = float(sample_rate_hz)
        self.channels = {c.name: c for c in channels}
        if "head" not in self.channels:
            raise ValueError("a run needs the head channel")
        self.slow_channels = {c.name: c for c in slow_channels}
        try:
            fh = h5py.File(self.path, "w-", libver="latest")
        except FileExistsError:
            raise DataError(f"{self.path}: already exists; a recorded run is never overwritten") from None
        except OSError as exc:
            raise DataError(f"{self.path}: cannot create ({exc.strerror or exc})") from None
        self._fh = fh
        self.n = 0
        self._closed = False
        chunk = CHUNK_SAMPLES if expected_samples is None else max(256, min(CHUNK_SAMPLES, int(expected_samples)))
        fh.attrs["NX_class"] = "NXroot"
        fh.attrs["default"] = "entry"
        fh.attrs["file_format"] = FILE_FORMAT
        fh.attrs["format_version"] = FORMAT_VERSION
        fh.attrs["creator"] = "velab"
        fh.attrs["creator_version"] = __version__
        fh.attrs["file_name"] = self.path.name
        fh.attrs["HDF5_Version"] = h5py.version.hdf5_version
        fh.attrs["h5py_version"] = h5py.version.version
        e = fh.create_group("entry")
        e.attrs["NX_class"] = "NXentry"
        e.attrs["default"] = "data"
        e.create_dataset("title", data=title)
        start = now_iso()
        e.create_dataset("start_time", data=np.bytes_(start.encode()), dtype=f"S{STATUS_LEN}")
        e.create_dataset("end_time", data=np.bytes_(b""), dtype=f"S{STATUS_LEN}")
        e.create_dataset("status", data=np.bytes_(status.encode()), dtype=f"S{STATUS_LEN}")
        e.create_dataset("status_reason", data=np.bytes_(b""), dtype=f"S{REASON_LEN}")
        pn = e.create_dataset("program_name", data="velab")
        pn.attrs["version"] = __version__

        data = e.create_group("data")
        data.attrs["NX_class"] = "NXdata"
        data.attrs["signal"] = "head"
        data.attrs["axes"] = ["time"]
        data.attrs["time_indices"] = 0
        self._ds: dict[str, h5py.Dataset] = {}
        tds = data.create_dataset("time", shape=(0,), maxshape=(None,), dtype="f8", chunks=(chunk,))
        tds.attrs["units"] = "s"
        tds.attrs["long_name"] = "time from the trigger"
        tds.attrs["sample_rate_hz"] = self.sample_rate_hz
        self._ds["time"] = tds
        inst = e.create_group("instrument")
        inst.attrs["NX_class"] = "NXinstrument"
        for c in channels:
            parent = fh.require_group(f"entry/{c.group}")
            if "NX_class" not in parent.attrs:
                parent.attrs["NX_class"] = "NXsensor"
            ds = parent.create_dataset(c.name, shape=(0,), maxshape=(None,), dtype=c.dtype, chunks=(chunk,))
            ds.attrs["units"] = c.units
            if c.long_name:
                ds.attrs["long_name"] = c.long_name
            self._ds[c.name] = ds
            if c.group != "data":
                data[c.name] = ds  # hard link: the NXdata group shows every fast channel
        for c in slow_channels:
            g = inst.require_group(c.name)
            g.attrs["NX_class"] = "NXlog"
            v = g.create_dataset("value", shape=(0,), maxshape=(None,), dtype=c.dtype, chunks=(256,))
            v.attrs["units"] = c.units
            tt = g.create_dataset("time", shape=(0,), maxshape=(None,), dtype="f8", chunks=(256,))
            tt.attrs["units"] = "s"
            tt.attrs["start"] = start
            self._ds[f"slow:{c.name}"] = v
            self._ds[f"slow_time:{c.name}"] = tt
        if calibration:
            cal = inst.require_group("calibration")
            cal.attrs["NX_class"] = "NXcollection"
            cal.attrs["calibration_json"] = json.dumps(calibration)
        inst.attrs["device_setup_json"] = json.dumps(device_setup or {})

        _sample_group(e, rig, material, noise_std_m)
        man = e.create_group("manoeuvre")
        man.attrs["NX_class"] = "NXcollection"
        mvals = {
            "beta": (rig.manoeuvre.beta_per_s, "1/s"),
            "gamma": (rig.manoeuvre.gamma, ""),
            "steady_flow": (rig.steady_flow_m3_s, "m^3/s"),
            "trigger_time": (trigger_time_s, "s"),
        }
        for k, v in (manoeuvre or {}).items():
            mvals[k] = v if isinstance(v, tuple) else (v, "")
        for name, (value, units) in mvals.items():
            d = man.create_dataset(name, data=value)
            d.attrs["units"] = units

        ev = e.create_group("events")
        ev.attrs["NX_class"] = "NXcollection"
        d = ev.create_dataset("time", shape=(0,), maxshape=(None,), dtype="f8", chunks=(256,))
        d.attrs["units"] = "s"
        ev.create_dataset("kind", shape=(0,), maxshape=(None,), dtype="S32", chunks=(256,))
        ev.create_dataset("message", shape=(0,), maxshape=(None,), dtype="S200", chunks=(256,))
        gp = e.create_group("gaps")
        gp.attrs["NX_class"] = "NXcollection"
        d = gp.create_dataset("sample_index", shape=(0,), maxshape=(None,), dtype="i8", chunks=(256,))
        d.attrs["units"] = "samples"
        d = gp.create_dataset("lost", shape=(0,), maxshape=(None,), dtype="i8", chunks=(256,))
        d.attrs["units"] = "samples"
        fits = e.create_group("fits")
        fits.attrs["NX_class"] = "NXcollection"
        notes = e.create_group("notes")
        notes.attrs["NX_class"] = "NXnote"
        notes.attrs["settings_json"] = json.dumps(settings or {}, default=str)
        notes.attrs["source_json"] = json.dumps(source or {}, default=str)
        self._trigger = trigger_time_s
        if swmr:
            fh.swmr_mode = True
        fh.flush()

    # -- streaming
    def append(self, time_s, **channels) -> None:
        """Append samples: ``time_s`` and one array per declared fast channel (same length)."""
        t = np.asarray(time_s, dtype=float).ravel()
        k = t.size
        if k == 0:
            return
        missing = set(self.channels) - set(channels)
        unknown = set(channels) - set(self.channels)
        if missing or unknown:
            raise ValueError(f"append: missing channels {sorted(missing)}, unknown {sorted(unknown)}")
        n0, n1 = self.n, self.n + k
        for name, values in channels.items():
            v = np.asarray(values).ravel()
            if v.size != k:
                raise ValueError(f"append: channel {name} has {v.size} samples, time has {k}")
            ds = self._ds[name]
            ds.resize((n1,))
            ds[n0:n1] = v
        ds = self._ds["time"]
        ds.resize((n1,))
        ds[n0:n1] = t  # time last: a reader never sees time without its samples
        self.n = n1

    def append_slow(self, name: str, time_s, values) -> None:
        t = np.atleast_1d(np.asarray(time_s, dtype=float))
        v = np.atleast_1d(np.asarray(values))
        vd, td = self._ds[f"slow:{name}"], self._ds[f"slow_time:{name}"]
        n0 = vd.shape[0]
        vd.resize((n0 + v.size,))
        vd[n0:] = v
        td.resize((n0 + t.size,))
        td[n0:] = t

    def event(self, time_s: float, kind: str, message: str = "") -> None:
        ev = self._fh["entry/events"]
        n = ev["time"].shape[0]
        for name, value in (("kind", np.bytes_(kind.encode()[:32])), ("message", np.bytes_(message.encode()[:200])), ("time", time_s)):
            ev[name].resize((n + 1,))
            ev[name][n] = value

    def gap(self, sample_index: int, lost: int) -> None:
        g = self._fh["entry/gaps"]
        n = g["lost"].shape[0]
        g["sample_index"].resize((n + 1,))
        g["sample_index"][n] = sample_index
        g["lost"].resize((n + 1,))
        g["lost"][n] = lost

    def set_trigger_time(self, time_s: float) -> None:
        """Overwrite /entry/manoeuvre/trigger_time (SWMR-safe: a pre-created scalar).

        A recorder writes its time axis before the trigger instant is known exactly
        (it is measured from the valve-position feedback after the manoeuvre)."""
        self._fh["entry/manoeuvre/trigger_time"][()] = float(time_s)
        self._trigger = float(time_s)

    def set_value(self, path: str, value) -> None:
        """Overwrite a pre-created scalar dataset under /entry (e.g. ``manoeuvre/trigger_host_time``)."""
        self._fh[f"entry/{path}"][()] = value

    def set_status(self, status: str, reason: str = "") -> None:
        e = self._fh["entry"]
        _set_str(e, "status", status, STATUS_LEN)
        _set_str(e, "status_reason", reason, REASON_LEN)

    def flush(self) -> None:
        self._fh.flush()

    def close(self, status: str = "completed", reason: str = "") -> None:
        if self._closed:
            return
        if status not in STATUSES:
            raise ValueError(f"unknown status {status!r}")
        try:
            e = self._fh["entry"]
            _set_str(e, "end_time", now_iso(), STATUS_LEN)
            self.set_status(status, reason)
            self._fh.flush()
        finally:
            self._closed = True
            self._fh.close()

    def __enter__(self) -> "RunWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if not self._closed:
            self.close("failed" if exc_type else "completed", "" if exc is None else str(exc)[:REASON_LEN])


def write_run(
    path: str | os.PathLike,
    rig: Rig,
    time_s: np.ndarray,
    head_m: np.ndarray,
    *,
    status: str,
    title: str = "",
    extra_channels: dict[str, tuple[np.ndarray, str]] | None = None,
    sample_rate_hz: float | None = None,
    overwrite: bool = False,
    **kwargs,
) -> Path:
    """Write a whole run at once (synthetic runs, imports). Same layout as a recording.

    ``overwrite`` replaces an existing file, atomically: it is only renamed over once
    the new file is complete, so a failure leaves the old one as it was.
    """
    time_s = np.asarray(time_s, dtype=float)
    if time_s.size < 2:
        raise DataError(f"{path}: a run needs at least 2 samples")
    path = Path(path)
    if path.exists() and not overwrite:
        raise DataError(f"{path}: already exists (use --force to replace it)")
    if not path.parent.is_dir():
        raise DataError(f"{path.parent}: output directory does not exist")
    rate = sample_rate_hz or 1.0 / float(np.median(np.diff(time_s)))
    channels = [HEAD] + [Channel(n, u) for n, (_, u) in (extra_channels or {}).items()]
    # Written under a temporary name and renamed: a half-written file never
    # appears under the run's name.
    tmp = path.with_name(f".{path.name}.part")
    tmp.unlink(missing_ok=True)
    w = RunWriter(tmp, rig, sample_rate_hz=rate, title=title, channels=tuple(channels), swmr=False,
                  status="recording", expected_samples=time_s.size, **kwargs)
    try:
        w.append(time_s, head=head_m, **{n: v for n, (v, _) in (extra_channels or {}).items()})
        w.close(status)
        os.replace(tmp, path)
    except BaseException:
        w.close("failed", "writing failed")
        tmp.unlink(missing_ok=True)
        raise
    return path
