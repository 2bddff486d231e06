"""DATAQ DI-series device profile from TOML (configs/devices/dataq_di2108.toml, dataq_di1100.toml, ...).

Each channel is an analogue input read in volts and turned into its loop signal and value: a 4-20 mA
transducer through a shunt resistor (``shunt_ohm``: signal in mA = volts / shunt, so the NAMUR NE43 rules
of velab.drivers.base apply to the loop current), or a voltage (the valve-position potentiometer: signal in
V, no open-loop rule). Every error is one line naming the file and the key (DataqProfileError).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from velab.configpath import load_config
from velab.drivers.base import NE43_OPEN_LOOP_MA, LoopCalibration, ProfileError
from velab.drivers.dataq_protocol import MODELS, ModelSpec, model
from velab.errors import ConfigError
from velab.tomlschema import Reader


class DataqProfileError(ProfileError, ConfigError):
    """A DATAQ profile is invalid (a DeviceError and a user-facing ConfigError)."""


@dataclass(frozen=True)
class DataqChannel:
    name: str
    input: int  # analogue input 0..n-1
    calibration: LoopCalibration  # signal (mA through the shunt, or V) -> value
    shunt_ohm: float | None = None  # None: a voltage input (signal = volts)
    head: bool = False
    stuck_s: float | None = None

    def signal(self, volts):
        """Volts at the input -> the calibration's signal (mA through the shunt, or volts)."""
        return volts * (1000.0 / self.shunt_ohm) if self.shunt_ohm else volts


@dataclass(frozen=True)
class DataqProfile:
    model: str = "DI-2108"
    channels: tuple[DataqChannel, ...] = ()
    enabled: tuple[str, ...] = ()
    rate_hz: float = 1000.0
    url: str | None = None
    baudrate: int = 115200  # ignored by USB CDC, a pty and socket://
    packet_size: int = -1  # ps code 0..7 (16..2048 bytes); -1 = auto from the byte rate
    digital_outputs: tuple[int, ...] = ()  # lines set as switches by endo (the valve trigger)
    command_timeout_s: float = 1.0
    data_timeout_s: float = 1.0
    reconnect: bool = True
    reconnect_timeout_s: float = 3.0
    poll_s: float = 0.05
    queue_blocks: int = 2000
    density_kg_m3: float = 998.2
    path: Path | None = None

    @property
    def spec(self) -> ModelSpec:
        return model(self.model)

    def channel(self, key: str | int) -> DataqChannel:
        for ch in self.channels:
            if ch.name == key or ch.input == key:
                return ch
        raise KeyError(f"no channel {key!r} in the DATAQ profile (have {', '.join(c.name for c in self.channels)})")


def default_profile(**overrides) -> DataqProfile:
    """Built in (no file): a DI-2108, pressure 4-20 mA through 250 ohm = 0..6 bar on input 0, valve position
    1..5 V = 0..100 % on input 1, the trigger on D0."""
    chans = (
        DataqChannel("pressure", 0, LoopCalibration(4.0, 20.0, 0.0, 6.0e5, "Pa", range_margin=0.02), 250.0, head=True),
        DataqChannel("valve_position", 1, LoopCalibration(1.0, 5.0, 0.0, 100.0, "%", "V", open_loop_below=None,
                                                          range_margin=0.02)),
    )
    base = DataqProfile(channels=chans, enabled=("pressure", "valve_position"), digital_outputs=(0,))
    return replace(base, **overrides)


def _pos(v):
    return None if v > 0 else "must be positive"


_CH_KEYS = {"input", "shunt_ohm", "signal_lo", "signal_hi", "value_lo", "value_hi", "units", "zero_offset",
            "open_loop_below", "range_margin", "head", "stuck_s"}


def load_profile(name_or_path: str | Path = "dataq_di2108") -> DataqProfile:
    """``devices/<name>.toml`` (along the config search path) or a path -> a typed DataqProfile."""
    path, doc = load_config("devices", name_or_path, error=DataqProfileError)
    r = Reader(path, doc, error=DataqProfileError)
    for k in doc:
        if k not in {"device", "acquisition", "digital", "timeouts", "reader", "fluid", "channels"}:
            raise r.fail(k, "unknown table")
    dev = r.table("device", True, allowed={"model", "url", "baudrate", "packet_size"}, where="device")
    acq = r.table("acquisition", True, allowed={"rate_hz", "channels"}, where="acquisition")
    dig = r.table("digital", False, allowed={"outputs"}, where="digital")
    tmo = r.table("timeouts", False, allowed={"command_s", "data_s", "reconnect", "reconnect_s", "poll_s"},
                  where="timeouts")
    rdr = r.table("reader", False, allowed={"queue_blocks"}, where="reader")
    fluid = r.table("fluid", False, allowed={"density_kg_m3"}, where="fluid")
    chans_doc = r.table("channels", True, where="channels")
    name = r.get(dev, "device", "model", str, check=lambda v: None if v in MODELS else
                 f"unsupported model (supported: {', '.join(MODELS)})")
    spec = MODELS[name]

    chans: list[DataqChannel] = []
    used: dict[int, str] = {}
    for cname, cd in chans_doc.items():
        where = f"channels.{cname}"
        if not isinstance(cd, dict):
            raise r.fail(where, "must be a table")
        r.check_keys(cd, where, _CH_KEYS)
        idx = r.get(cd, where, "input", int, check=lambda v: None if 0 <= v < spec.analog_inputs
                    else f"must be 0..{spec.analog_inputs - 1} (the {name}'s analogue inputs)")
        if idx in used:
            raise r.fail(f"{where}.input", f"input {idx} is already used by channels.{used[idx]}")
        used[idx] = cname
        shunt = r.get(cd, where, "shunt_ohm", float, None, check=_pos)
        s_lo = r.get(cd, where, "signal_lo", float)
        s_hi = r.get(cd, where, "signal_hi", float)
        if s_hi <= s_lo:
            raise r.fail(f"{where}.signal_hi", "must be greater than signal_lo")
        fs_signal = spec.range_v * (1000.0 / shunt if shunt else 1.0)
        if max(abs(s_lo), abs(s_hi)) > fs_signal:
            raise r.fail(f"{where}.signal_hi", f"outside the +-{spec.range_v:g} V input range "
                         f"(+-{fs_signal:.4g} {'mA through the shunt' if shunt else 'V'})")
        v_lo = r.get(cd, where, "value_lo", float)
        v_hi = r.get(cd, where, "value_hi", float)
        if v_hi == v_lo:
            raise r.fail(f"{where}.value_hi", "must differ from value_lo")
        units = r.get(cd, where, "units", str)
        olb = r.get(cd, where, "open_loop_below", float, NE43_OPEN_LOOP_MA if shunt else None)
        margin = r.get(cd, where, "range_margin", float, 0.0, check=lambda v: None if 0 <= v < 1 else "must be in [0, 1)")
        head = r.get(cd, where, "head", bool, False)
        if head and units != "Pa":
            raise r.fail(f"{where}.head", f"needs units = \"Pa\" (got {units!r})")
        cal = LoopCalibration(s_lo, s_hi, v_lo, v_hi, units, "mA" if shunt else "V",
                              r.get(cd, where, "zero_offset", float, 0.0), olb, margin)
        chans.append(DataqChannel(cname, idx, cal, shunt, head, r.get(cd, where, "stuck_s", float, None, check=_pos)))
    if not chans:
        raise r.fail("channels", "define at least one channel")

    names = {c.name for c in chans}
    enabled = r.get(acq, "acquisition", "channels", list)
    if not enabled or not all(isinstance(e, str) for e in enabled):
        raise r.fail("acquisition.channels", "list the channel names to acquire")
    for e in enabled:
        if e not in names:
            raise r.fail("acquisition.channels", f"{e!r} is not defined under [channels] (have {', '.join(sorted(names))})")
    if len(set(enabled)) != len(enabled):
        raise r.fail("acquisition.channels", "lists a channel twice")
    n_an = len(enabled)
    lo, hi = spec.rate_bounds(n_an)
    rate = r.get(acq, "acquisition", "rate_hz", float, check=lambda v: None if lo <= v <= hi else
                 f"must be {lo:.4g}..{hi:.6g} Hz for the {name} with {n_an} channel(s) (srate table, protocol p.48)")
    outputs = r.get(dig, "digital", "outputs", list, [])
    if outputs and not spec.digital_io:
        raise r.fail("digital.outputs", f"the {name} has no digital outputs (protocol p.57)")
    if not all(isinstance(o, int) and not isinstance(o, bool) and 0 <= o < spec.digital_lines for o in outputs):
        raise r.fail("digital.outputs", f"list digital lines 0..{spec.digital_lines - 1}")
    return DataqProfile(
        model=name, channels=tuple(chans), enabled=tuple(enabled), rate_hz=rate,
        url=r.get(dev, "device", "url", str, None) or None,
        baudrate=r.get(dev, "device", "baudrate", int, 115200, check=_pos),
        packet_size=r.get(dev, "device", "packet_size", int, -1,
                          check=lambda v: None if -1 <= v <= 7 else "must be 0..7 (ps 16..2048 bytes) or -1 (auto)"),
        digital_outputs=tuple(sorted(set(outputs))),
        command_timeout_s=r.get(tmo, "timeouts", "command_s", float, 1.0, check=_pos),
        data_timeout_s=r.get(tmo, "timeouts", "data_s", float, 1.0, check=_pos),
        reconnect=r.get(tmo, "timeouts", "reconnect", bool, True),
        reconnect_timeout_s=r.get(tmo, "timeouts", "reconnect_s", float, 3.0, check=_pos),
        poll_s=r.get(tmo, "timeouts", "poll_s", float, 0.05, check=lambda v: None if 0 < v <= 1 else "must be in (0, 1] s"),
        queue_blocks=r.get(rdr, "reader", "queue_blocks", int, 2000, check=_pos),
        density_kg_m3=r.get(fluid, "fluid", "density_kg_m3", float, 998.2, check=_pos),
        path=path,
    )
