"""Writing run files: :class:`RunWriter` streams a recording (SWMR); :func:`write_run` writes a whole run.

Every dataset is created before the first sample (chunked, resizable), the time
axis is made a dimension scale attached to every fast channel, then the file
switches to SWMR mode so readers can follow it. After that the writer only
appends and overwrites pre-created fixed-size values (HDF5 forbids new objects
and variable-length data under SWMR).

One source of truth: the manoeuvre given to the writer (the commanded one) is
written into the rig snapshot and into ``/entry/manoeuvre`` from one object.
"""

from __future__ import annotations

import os
import platform
import time as _time
from importlib import metadata
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from velab.version import __version__
from velab.config import Material
from velab.rig import Manoeuvre, Rig
from velab.errors import DataError
from velab.runfiles import layout as L
from velab.runfiles.layout import udunits
from velab.runfiles.probe import trust


@dataclass(frozen=True)
class Channel:
    """A fast channel sampled on the run's time axis (or, in ``slow_channels``, an NXlog)."""

    name: str
    units: str
    dtype: str = "f8"
    long_name: str = ""
    group: str = "data"  # "data" (NXdata) or an instrument subgroup such as "instrument/pressure_transducer"


HEAD = Channel("head", "m", "f8", "pressure head at the transducer (absolute, above the transducer)")
DEFAULT_CHANNELS = (HEAD,)


def software_versions() -> dict[str, str]:
    """Versions of velab and the libraries a run's numbers depend on."""
    out = {"velab": __version__, "python": platform.python_version(), "HDF5": h5py.version.hdf5_version}
    for dist in ("numpy", "scipy", "h5py", "pymodbus", "pyserial"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "not installed"
    return out


def effective_rig(rig: Rig, manoeuvre: dict | None) -> Rig:
    """The rig with the commanded manoeuvre (beta, gamma of ``manoeuvre``), the one the run used."""
    if not manoeuvre:
        return rig
    def value(key, default):
        v = manoeuvre.get(key, default)
        return float(v[0] if isinstance(v, tuple) else v)
    m = Manoeuvre(beta_per_s=value("beta", rig.manoeuvre.beta_per_s), gamma=value("gamma", rig.manoeuvre.gamma))
    return rig if m == rig.manoeuvre else rig.with_changes(manoeuvre=m)


def _dataset(g: h5py.Group, name: str, value, units: str) -> h5py.Dataset:
    d = g.create_dataset(name, data=value)
    d.attrs["units"] = udunits(units)
    return d


def _sample_group(e: h5py.Group, rig: Rig, material: Material | None, noise_std_m: float | None) -> None:
    s = e.create_group("sample")
    s.attrs["NX_class"] = "NXsample"
    L.write_str(s, "name", rig.name)
    L.write_json(s, "rig_json", rig.to_dict())
    p = rig.pipe
    for name, value, units in (
        ("pipe_length", p.length_m, "m"),
        ("inner_diameter", p.inner_diameter_m, "m"),
        ("wall_thickness", p.wall_thickness_m, "m"),
        ("constraint_coefficient", p.constraint_alpha, "1"),
        ("pressure_rating", p.pressure_rating_pa if p.pressure_rating_pa is not None else float("nan"), "Pa"),
        ("fluid_density", rig.fluid.density_kg_m3, "kg/m3"),
        ("fluid_kinematic_viscosity", rig.fluid.kinematic_viscosity_m2_s, "m2/s"),
        ("steady_flow", rig.steady_flow_m3_s, "m3/s"),
        ("reservoir_head", rig.reservoir_head_m, "m"),
        ("nominal_wave_speed", rig.nominal_wave_speed_m_s, "m/s"),
        ("transducer_full_scale", rig.transducer.full_scale_pa, "Pa"),
    ):
        _dataset(s, name, float(value), units)
    L.write_str(s, "pipe_material", p.material)
    s.attrs["noise_std_m"] = float("nan") if noise_std_m is None else float(noise_std_m)
    if material is None:
        return
    L.write_json(s, "material_json", material.to_dict())
    m = s.create_group("material")
    m.attrs["NX_class"] = "NXcollection"
    L.write_str(m, "name", material.name)
    L.write_str(m, "model", material.model_name)
    for name, values, units in (
        ("wave_speed", [material.wave_speed_m_s], "m/s"),
        ("E", [el.E_pa for el in material.elements], "Pa"),
        ("eta", [el.eta_pa_s for el in material.elements], "Pa.s"),
        ("tau", [el.tau_s for el in material.elements], "s"),
        ("J", [el.J_per_pa for el in material.elements], "Pa-1"),
    ):
        _dataset(m, name, np.asarray(values, dtype=float), units)


class RunWriter:
    """Streams a run into its HDF5 file as it is recorded.

    ``append`` adds samples of the fast channels; ``append_slow`` a reading of
    a slow device (NXlog); ``event`` a time-stamped event; ``gap`` lost samples
    (never interpolated); ``flush`` makes everything so far durable;
    ``close(status)`` writes the end time and status.

    Each head channel of a transducer of the rig (``head``, ``head_NAME``: ``Rig.section_channel``) carries
    ``@transducer`` (its name) and ``@position_m`` (its distance from the upstream reservoir).

    Keyword arguments added in format 2.0 (all optional): ``bench`` (the bench
    configuration's contents), ``device_profiles`` (name -> profile contents),
    ``devices`` (name -> identity read from the device), ``file_name`` (the
    name the file will have, for writers that rename a temporary file).

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
        bench: dict | None = None,
        device_profiles: dict | None = None,
        devices: dict | None = None,
        file_name: str | None = None,
    ):
        if not sample_rate_hz > 0:
            raise ValueError("sample_rate_hz must be positive")
        self.path = Path(path)
        self.sample_rate_hz = float(sample_rate_hz)
        self.channels = {c.name: c for c in channels}
        if "head" not in self.channels:
            raise ValueError("a run needs the head channel")
        self.slow_channels = {c.name: c for c in slow_channels}
        self.rig = effective_rig(rig, manoeuvre)
        try:
            fh = h5py.File(self.path, "w-", libver=L.LIBVER)
        except FileExistsError:
            raise DataError(f"{self.path}: already exists; a recorded run is never overwritten") from None
        except OSError as exc:
            raise DataError(f"{self.path}: cannot create ({exc.strerror or exc})") from None
        self._fh = fh
        self.n = 0
        self._closed = False
        self._swmr = bool(swmr)
        self._start_epoch = _time.time()
        try:
            self._create(fh, title, channels, slow_channels, material, noise_std_m, trigger_time_s, manoeuvre,
                         device_setup, settings, source, calibration, status, expected_samples, bench,
                         device_profiles, devices, file_name)
            if swmr:
                fh.swmr_mode = True
            fh.flush()
        except BaseException:
            fh.close()
            self.path.unlink(missing_ok=True)
            raise

    def _create(self, fh, title, channels, slow_channels, material, noise_std_m, trigger_time_s, manoeuvre,
                device_setup, settings, source, calibration, status, expected_samples, bench, device_profiles,
                devices, file_name) -> None:
        fixed = self._swmr  # sizes for strings rewritten under SWMR; None = variable length
        chunk = L.CHUNK_SAMPLES if expected_samples is None else max(256, min(L.CHUNK_SAMPLES, int(expected_samples)))
        fh.attrs["NX_class"] = "NXroot"
        fh.attrs["default"] = "entry"
        fh.attrs["file_format"] = L.FILE_FORMAT
        fh.attrs["format_version"] = L.FORMAT_VERSION
        fh.attrs["creator"] = "velab"
        fh.attrs["creator_version"] = __version__
        fh.attrs["file_name"] = file_name or self.path.name
        fh.attrs["file_time"] = L.iso_of(self._start_epoch)
        fh.attrs["HDF5_Version"] = h5py.version.hdf5_version
        fh.attrs["h5py_version"] = h5py.version.version
        e = fh.create_group("entry")
        e.attrs["NX_class"] = "NXentry"
        e.attrs["default"] = "data"
        L.write_str(e, "title", title)
        start = L.iso_of(self._start_epoch)
        L.write_str(e, "start_time", start)
        L.write_str(e, "end_time", "", L.TIME_LEN if fixed else None)
        L.write_str(e, "status", status, L.STATUS_LEN if fixed else None)
        L.write_str(e, "status_reason", "", L.REASON_LEN if fixed else None)
        pn = L.write_str(e, "program_name", "velab")
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
        tds.make_scale("time")  # xarray / netCDF readers see a real axis
        self._ds["time"] = tds
        inst = e.create_group("instrument")
        inst.attrs["NX_class"] = "NXinstrument"
        heads = {self.rig.section_channel(sec): sec for sec in self.rig.sections}  # head, head_NAME
        for c in channels:
            parent = fh.require_group(f"entry/{c.group}")
            if "NX_class" not in parent.attrs:
                parent.attrs["NX_class"] = "NXsensor"
            ds = parent.create_dataset(c.name, shape=(0,), maxshape=(None,), dtype=c.dtype, chunks=(chunk,))
            ds.attrs["units"] = udunits(c.units)
            if c.long_name:
                ds.attrs["long_name"] = c.long_name
            ds.dims[0].attach_scale(tds)
            if c.name in heads:  # a transducer's head: which one, and where along the pipe
                ds.attrs["transducer"] = heads[c.name].name
                ds.attrs["position_m"] = float(heads[c.name].position_m)
            self._ds[c.name] = ds
            if c.group != "data":
                data[c.name] = ds  # hard link: the NXdata group shows every fast channel
        for c in slow_channels:
            g = inst.require_group(c.name)
            g.attrs["NX_class"] = "NXlog"
            v = g.create_dataset("value", shape=(0,), maxshape=(None,), dtype=c.dtype, chunks=(256,))
            v.attrs["units"] = udunits(c.units)
            if c.long_name:
                v.attrs["long_name"] = c.long_name
            tt = g.create_dataset("time", shape=(0,), maxshape=(None,), dtype="f8", chunks=(256,))
            tt.attrs["units"] = "s"
            tt.attrs["start"] = start  # NXlog: time is relative to @start (the host clock)
            at = g.create_dataset("axis_time", shape=(0,), maxshape=(None,), dtype="f8", chunks=(256,))
            at.attrs["units"] = "s"
            at.attrs["long_name"] = "the same instants on the run's time axis (data/time)"
            self._ds[f"slow:{c.name}"] = v
            self._ds[f"slow_time:{c.name}"] = tt
            self._ds[f"slow_axis:{c.name}"] = at
        if calibration:
            cal = inst.require_group("calibration")
            cal.attrs["NX_class"] = "NXcollection"
            L.write_json(cal, "calibration_json", calibration)
        L.write_json(inst, "device_setup_json", device_setup or {})
        if bench is not None:
            L.write_json(inst, "bench_json", bench)
        if device_profiles is not None:
            L.write_json(inst, "device_profiles_json", device_profiles)
        if devices is not None:
            L.write_json(inst, "devices_json", devices)

        _sample_group(e, self.rig, material, noise_std_m)
        man = e.create_group("manoeuvre")
        man.attrs["NX_class"] = "NXcollection"
        # beta and gamma come from the rig written above: the two copies cannot disagree
        mvals = dict(manoeuvre or {})
        mvals["beta"] = (self.rig.manoeuvre.beta_per_s, "s-1")
        mvals["gamma"] = (self.rig.manoeuvre.gamma, "1")
        mvals.setdefault("steady_flow", (self.rig.steady_flow_m3_s, "m3/s"))
        mvals["trigger_time"] = (float(trigger_time_s), "s")
        for name, v in mvals.items():
            value, units = v if isinstance(v, tuple) else (v, "1")
            _dataset(man, name, value, units)

        ev = e.create_group("events")
        ev.attrs["NX_class"] = "NXcollection"
        d = ev.create_dataset("time", shape=(0,), maxshape=(None,), dtype="f8", chunks=(256,))
        d.attrs["units"] = "s"
        if fixed:
            opts = {"chunks": (64,), "compression": "gzip", "compression_opts": 1}
            ev.create_dataset("kind", shape=(0,), maxshape=(None,), dtype=L.fixed_str(L.KIND_LEN), **opts)
            ev.create_dataset("message", shape=(0,), maxshape=(None,), dtype=L.fixed_str(L.MESSAGE_LEN), **opts)
        else:
            ev.create_dataset("kind", shape=(0,), maxshape=(None,), dtype=L.VLEN_STR, chunks=(256,))
            ev.create_dataset("message", shape=(0,), maxshape=(None,), dtype=L.VLEN_STR, chunks=(256,))
        gp = e.create_group("gaps")
        gp.attrs["NX_class"] = "NXcollection"
        for name, long_name in (("sample_index", "index of the first sample after the gap"),
                                ("lost", "samples missing before it")):
            d = gp.create_dataset(name, shape=(0,), maxshape=(None,), dtype="i8", chunks=(256,))
            d.attrs["units"] = "1"
            d.attrs["long_name"] = long_name
        fits = e.create_group("fits")
        fits.attrs["NX_class"] = "NXcollection"
        notes = e.create_group("notes")
        notes.attrs["NX_class"] = "NXnote"
        L.write_json(notes, "settings_json", settings or {})
        L.write_json(notes, "source_json", source or {})
        L.write_json(notes, "versions_json", software_versions())
        self._trigger = float(trigger_time_s)

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

    def append_slow(self, name: str, time_s, values, *, epoch_s=None) -> None:
        """A slow device's readings: ``time_s`` on the run's time axis, ``epoch_s`` their host clock
        (time.time(); default: now for the last reading, the others before it by their axis times)."""
        t = np.atleast_1d(np.asarray(time_s, dtype=float))
        v = np.atleast_1d(np.asarray(values))
        if epoch_s is None:
            epoch = _time.time() + (t - t[-1]) if t.size else t
        else:
            epoch = np.atleast_1d(np.asarray(epoch_s, dtype=float))
        for key, arr in ((f"slow:{name}", v), (f"slow_time:{name}", epoch - self._start_epoch),
                         (f"slow_axis:{name}", t)):
            ds = self._ds[key]
            n0 = ds.shape[0]
            ds.resize((n0 + arr.size,))
            ds[n0:] = arr

    def event(self, time_s: float, kind: str, message: str = "") -> None:
        ev = self._fh["entry/events"]
        if ev["message"].dtype.kind == "S":  # fixed-size (SWMR): long messages continue on more rows
            rows = [(L.encode_fixed(kind, L.KIND_LEN), p) for p in L.split_fixed(message, L.MESSAGE_LEN)]
            rows = rows[:1] + [(L.CONTINUED.encode(), p) for _, p in rows[1:]]
        else:
            rows = [(kind, message)]
        n = ev["time"].shape[0]
        for i, (k, m) in enumerate(rows):
            for name, value in (("kind", k), ("message", m), ("time", time_s)):
                ev[name].resize((n + i + 1,))
                ev[name][n + i] = value

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
        L.set_str(e, "status", status)
        L.set_str(e, "status_reason", reason)

    def flush(self) -> None:
        # every fast channel's data and extent first, time's last (H5Dflush, one after the other): a file-level flush
        # writes the datasets' metadata in the library's own order, and a process killed inside it left time's extent
        # 540 samples ahead of the channels' -- a SWMR reader following time saw samples the file never held
        for name in self.channels:
            self._ds[name].flush()
        self._ds["time"].flush()
        self._fh.flush()

    def close(self, status: str = "completed", reason: str = "") -> None:
        if self._closed:
            return
        if status not in L.STATUSES:
            raise ValueError(f"unknown status {status!r}")
        try:
            L.set_str(self._fh["entry"], "end_time", L.now_iso())
            self.set_status(status, reason)
            self._fh.flush()
        finally:
            self._closed = True
            self._fh.close()
        trust(self.path)

    def __enter__(self) -> "RunWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if not self._closed:
            self.close("failed" if exc_type else "completed", "" if exc is None else str(exc))


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

    Written under a temporary name and renamed, so a half-written file never
    appears under the run's name; ``overwrite`` replaces an existing file only
    once the new one is complete.
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
    tmp = path.with_name(f".{path.name}.part")
    tmp.unlink(missing_ok=True)
    w = RunWriter(tmp, rig, sample_rate_hz=rate, title=title, channels=tuple(channels), swmr=False,
                  status="recording", expected_samples=time_s.size, file_name=path.name, **kwargs)
    try:
        w.append(time_s, head=head_m, **{n: v for n, (v, _) in (extra_channels or {}).items()})
        w.close(status)
        os.replace(tmp, path)
    except BaseException:
        w.close("failed", "writing failed")
        tmp.unlink(missing_ok=True)
        raise
    return path
