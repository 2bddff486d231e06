"""What a recorded run file holds: its channels and the snapshot that makes it self-describing.

The commanded manoeuvre is THE manoeuvre: the rig written into the file carries it, so
``/entry/manoeuvre/beta`` and ``/entry/sample@rig_json`` say the same, and an offline
``velab fit`` uses what the valve was told to do.

Every transducer of the rig has its channels (velab.recording.transducers): the valve's are
``FAST_CHANNELS``' ``head``, ``pressure``, ``pressure_raw``, ``pressure_quality``; each other one the
same with ``_NAME`` (``head_mid`` in ``data``, the rest in ``instrument/pressure_transducer_mid``).
"""

from __future__ import annotations

import datetime as _dt
from importlib import metadata
from pathlib import Path

from velab.recording.transducers import TransducerChannel
from velab.rig import Manoeuvre, Rig
from velab.runfiles.writer import HEAD, Channel, RunWriter

VERSIONED = ("velab", "numpy", "scipy", "h5py", "pymodbus", "pyserial")
INST = "instrument/pressure_transducer"
FAST_CHANNELS = (
    HEAD,
    Channel("valve_position", "%", "f8", "measured valve opening (position feedback)", "instrument/valve"),
    Channel("pressure", "Pa", "f8", "gauge pressure at the transducer", INST),
    Channel("pressure_raw", "counts", "i4", "ADC counts of the pressure channel", INST),
    Channel("pressure_quality", "", "u1", "per-sample quality code (velab.drivers.blocks.QUALITY_CODES; 0 = ok)", INST),
    Channel("valve_position_raw", "counts", "i4", "ADC counts of the position channel", "instrument/valve"),
    Channel("valve_position_quality", "", "u1", "per-sample quality code of the position feedback (0 = ok)",
            "instrument/valve"),
    Channel("sample_index", "samples", "i8", "device sample counter (gaps included)", "instrument/adc"),
    Channel("host_time", "s", "f8", "host epoch time of the sample (from the block's arrival)", "instrument/adc"),
)
SLOW_CHANNELS = (Channel("flow", "m^3/s"), Channel("valve_state", "", "i4"), Channel("valve_opening", "%"))


def transducer_channels(t: TransducerChannel) -> tuple[Channel, ...]:
    """The fast channels of a transducer other than the valve's (``head_NAME``, ``pressure_NAME`` ...)."""
    where = f"{t.name} ({t.position_m:g} m from the reservoir)"
    inst = f"{INST}_{t.name}"
    return (
        Channel(t.channel("head"), "m", "f8", f"pressure head at the transducer {where} (absolute)"),
        Channel(t.channel("pressure"), "Pa", "f8", f"gauge pressure at the transducer {where}", inst),
        Channel(t.channel("pressure_raw"), "counts", "i4", f"ADC counts of the transducer {t.name}'s channel", inst),
        Channel(t.channel("pressure_quality"), "", "u1", f"per-sample quality code of the transducer {t.name} "
                "(velab.drivers.blocks.QUALITY_CODES; 0 = ok)", inst),
    )


def fast_channels(transducers: tuple[TransducerChannel, ...] = ()) -> tuple[Channel, ...]:
    """The run file's fast channels: ``FAST_CHANNELS`` and each other transducer's (the valve's is in them)."""
    return FAST_CHANNELS + tuple(c for t in transducers if not t.at_valve for c in transducer_channels(t))


def versions() -> dict:
    out = {}
    for name in VERSIONED:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


def commanded_rig(rig: Rig, beta: float, gamma: float) -> Rig:
    """The rig with the manoeuvre the valve is commanded to run (the one the fit must use)."""
    return rig.with_changes(manoeuvre=Manoeuvre(beta_per_s=beta, gamma=gamma))


def run_file_name(out_dir: Path, run_number: int) -> Path:
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    n = max(1, int(run_number))
    while True:
        p = Path(out_dir) / f"{stamp}_run{n:03d}.h5"
        if not p.exists():
            return p
        n += 1


def bench_snapshot(bench, roles: dict, profiles: dict, identities: dict, sim=None) -> dict:
    """The bench config's contents (and its file's text), the roles, each device's profile
    contents and identity, the library versions, and the simulator's config if simulated."""
    d = {"bench": bench.to_dict(), "roles": roles, "profiles": profiles, "identities": identities,
         "versions": versions()}
    if bench.path and Path(bench.path).is_file():
        try:
            d["bench_toml"] = Path(bench.path).read_text()
        except OSError:
            pass
    if sim is not None:
        d["simulator"] = {k: v for k, v in sim.config.items() if k != "devices"}
        d["simulator"]["clock"] = type(sim.clock).__name__
        d["simulator"]["clock_scale"] = getattr(sim.clock, "scale", 1.0)
    return d


def create_run_file(path: Path, rig: Rig, settings, *, fs: float, manoeuvre: tuple[float, float, float],
                    steady_head: float, steady_flow: float, predicted_peak: float, ceiling: float,
                    device_setup: dict, calibration: dict, source: dict, armed_timeout_s: float,
                    transducers: tuple[TransducerChannel, ...] = ()) -> RunWriter:
    beta, gamma, end = manoeuvre
    man = {"end_position": (end, "%"), "beta": (beta, "1/s"), "gamma": (gamma, ""),
           "planned_trigger_time": (0.0, "s"), "trigger_host_time": (float("nan"), "s"),
           "steady_head": (steady_head, "m"), "measured_steady_flow": (steady_flow, "m^3/s"),
           "predicted_peak_head": (predicted_peak, "m"), "ceiling_head": (ceiling, "m"),
           # the stroke measured on the valve-position channel (velab.recording.stroke), NaN until measured
           "measured_beta": (float("nan"), "1/s"), "measured_gamma": (float("nan"), ""),
           "measured_end_position": (float("nan"), "%"), "measured_stroke_rms": (float("nan"), "%")}
    snapshot = settings.to_dict() | {"rig": rig.name, "armed_timeout_in_force_s": armed_timeout_s,
                                     # the bench's channel map as it was in force (velab.recording.transducers)
                                     "transducers": [{"name": t.name, "position_m": t.position_m, "head": t.head,
                                                      "adc_channel": t.adc_channel} for t in transducers]}
    s = settings
    return RunWriter(
        path, commanded_rig(rig, beta, gamma), sample_rate_hz=fs, title=s.title or f"water-hammer run {path.stem}",
        channels=fast_channels(transducers), slow_channels=SLOW_CHANNELS, material=None, trigger_time_s=0.0, manoeuvre=man,
        # the bench, profiles and identities go to their own datasets; device_setup keeps the rest
        device_setup={k: v for k, v in device_setup.items() if k not in ("bench", "profiles", "identities")},
        settings=snapshot, source=source | {"versions": device_setup.get("versions")},
        calibration=calibration, swmr=True, expected_samples=int((s.pretrigger_s + s.duration_s) * fs),
        bench=device_setup.get("bench"), device_profiles=device_setup.get("profiles"),
        devices=device_setup.get("identities"),
    )
