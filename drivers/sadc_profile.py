"""SADC-4 streaming-ADC profile: channels, calibrations, timeouts, from TOML (configs/devices/streaming_adc.toml).

Every error is one line naming the file and the key (StreamingADCProfileError, a ConfigError).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from velab.configpath import load_config
from velab.drivers.base import LoopCalibration, ProfileError
from velab.drivers.sadc_protocol import MAX_BLOCK, MAX_CHANNELS, RANGES_FS, RATE_MAX_HZ, RATE_MIN_HZ
from velab.errors import ConfigError
from velab.tomlschema import Reader


class StreamingADCProfileError(ProfileError, ConfigError):
    """A streaming-ADC profile is invalid (a DeviceError and a user-facing ConfigError)."""


@dataclass(frozen=True)
class ChannelProfile:
    name: str
    index: int  # ADC input 0..3
    range: str  # "25MA" or "10V"
    calibration: LoopCalibration
    head: bool = False  # also offer pressure head (m) for this channel (values in Pa)
    stuck_s: float | None = None  # identical counts for this long: STALE (stuck sensor); None = off

    @property
    def full_scale(self) -> float:
        return RANGES_FS[self.range][0]


@dataclass(frozen=True)
class StreamingADCProfile:
    channels: tuple[ChannelProfile, ...]  # every defined input
    enabled: tuple[str, ...]  # names acquired by default, in any order
    rate_hz: float = 10_000.0
    block_samples: int = 0  # 0 = auto
    url: str | None = None
    baudrate: int = 921_600
    model: str = "VELAB SADC-4"
    command_timeout_s: float = 1.0
    data_timeout_s: float = 1.0
    reconnect: bool = True
    reconnect_timeout_s: float = 3.0
    poll_s: float = 0.05
    queue_blocks: int = 2000
    density_kg_m3: float = 998.2
    path: Path | None = None

    def channel(self, key: str | int) -> ChannelProfile:
        for ch in self.channels:
            if ch.name == key or ch.index == key:
                return ch
        raise KeyError(f"no channel {key!r} in the streaming ADC profile (have {', '.join(c.name for c in self.channels)})")


def default_profile(**overrides) -> StreamingADCProfile:
    """A built-in profile (no file): pressure 4-20 mA = 0..6 bar, valve 4-20 mA = 0..100 %, two spares."""
    chans = (
        ChannelProfile("pressure", 0, "25MA", LoopCalibration(4.0, 20.0, 0.0, 6.0e5, "Pa", range_margin=0.02), head=True,
                       stuck_s=0.1),
        ChannelProfile("valve_position", 1, "25MA", LoopCalibration(4.0, 20.0, 0.0, 100.0, "%", range_margin=0.02),
                       stuck_s=0.1),
        ChannelProfile("spare_2", 2, "25MA", LoopCalibration(4.0, 20.0, 4.0, 20.0, "mA")),
        ChannelProfile("spare_3", 3, "25MA", LoopCalibration(4.0, 20.0, 4.0, 20.0, "mA")),
    )
    base = StreamingADCProfile(channels=chans, enabled=("pressure", "valve_position"))
    return replace(base, **overrides)


def _pos(v):
    return None if v > 0 else "must be positive"


def load_profile(name_or_path: str | Path = "streaming_adc") -> StreamingADCProfile:
    """Load ``devices/<name>.toml`` (along the config search path) or a path into a typed profile.

    Every error is one line naming the file and the key.
    """
    path, doc = load_config("devices", name_or_path, error=StreamingADCProfileError)
    r = Reader(path, doc, error=StreamingADCProfileError)
    for k in doc:
        if k not in {"device", "acquisition", "timeouts", "reader", "fluid", "channels"}:
            raise r.fail(k, "unknown table")
    dev = r.table("device", False, allowed={"model", "url", "baudrate"}, where="device")
    acq = r.table("acquisition", True, allowed={"rate_hz", "channels", "block_samples"}, where="acquisition")
    tmo = r.table("timeouts", False, allowed={"command_s", "data_s", "reconnect", "reconnect_s", "poll_s"}, where="timeouts")
    rdr = r.table("reader", False, allowed={"queue_blocks"}, where="reader")
    fluid = r.table("fluid", False, allowed={"density_kg_m3"}, where="fluid")
    chans_doc = r.table("channels", True, where="channels")

    chans: list[ChannelProfile] = []
    used: dict[int, str] = {}
    ch_keys = {"index", "range", "signal_lo", "signal_hi", "value_lo", "value_hi", "units", "zero_offset",
               "open_loop_below", "range_margin", "head", "stuck_s"}
    for name, cd in chans_doc.items():
        where = f"channels.{name}"
        if not isinstance(cd, dict):
            raise r.fail(where, "must be a table")
        for k in cd:
            if k not in ch_keys:
                raise r.fail(f"{where}.{k}", f"unknown key (allowed: {', '.join(sorted(ch_keys))})")
        idx = r.get(cd, where, "index", int, check=lambda v: None if 0 <= v < MAX_CHANNELS else "must be 0..3")
        if idx in used:
            raise r.fail(f"{where}.index", f"input {idx} is already used by channels.{used[idx]}")
        used[idx] = name
        rng = r.get(cd, where, "range", str, "25MA", check=lambda v: None if v in RANGES_FS else f"must be one of {', '.join(RANGES_FS)}")
        s_lo = r.get(cd, where, "signal_lo", float)
        s_hi = r.get(cd, where, "signal_hi", float)
        if s_hi <= s_lo:
            raise r.fail(f"{where}.signal_hi", "must be greater than signal_lo")
        if max(abs(s_lo), abs(s_hi)) > RANGES_FS[rng][0]:
            raise r.fail(f"{where}.signal_hi", f"outside the {rng} input range")
        v_lo = r.get(cd, where, "value_lo", float)
        v_hi = r.get(cd, where, "value_hi", float)
        if v_hi == v_lo:
            raise r.fail(f"{where}.value_hi", "must differ from value_lo")
        units = r.get(cd, where, "units", str)
        zero = r.get(cd, where, "zero_offset", float, 0.0)
        olb_default = 3.6 if rng.endswith("MA") else None
        olb = r.get(cd, where, "open_loop_below", float, olb_default)
        margin = r.get(cd, where, "range_margin", float, 0.0, check=lambda v: None if 0 <= v < 1 else "must be in [0, 1)")
        head = r.get(cd, where, "head", bool, False)
        if head and units != "Pa":
            raise r.fail(f"{where}.head", f"needs units = \"Pa\" (got {units!r})")
        stuck = r.get(cd, where, "stuck_s", float, None, check=_pos)
        cal = LoopCalibration(s_lo, s_hi, v_lo, v_hi, units, RANGES_FS[rng][1], zero, olb, margin)
        chans.append(ChannelProfile(name, idx, rng, cal, head, stuck))
    if not chans:
        raise r.fail("channels", "define at least one channel")

    names = {c.name for c in chans}
    enabled = r.get(acq, "acquisition", "channels", list)
    if not enabled or len(enabled) > MAX_CHANNELS or not all(isinstance(e, str) for e in enabled):
        raise r.fail("acquisition.channels", "list 1 to 4 channel names")
    for e in enabled:
        if e not in names:
            raise r.fail("acquisition.channels", f"{e!r} is not defined under [channels] (have {', '.join(sorted(names))})")
    if len(set(enabled)) != len(enabled):
        raise r.fail("acquisition.channels", "lists a channel twice")
    rate = r.get(acq, "acquisition", "rate_hz", float,
                 check=lambda v: None if RATE_MIN_HZ <= v <= RATE_MAX_HZ else f"must be {RATE_MIN_HZ}..{RATE_MAX_HZ} Hz")
    block = r.get(acq, "acquisition", "block_samples", int, 0,
                  check=lambda v: None if 0 <= v <= MAX_BLOCK else f"must be 0 (auto) .. {MAX_BLOCK}")
    url = r.get(dev, "device", "url", str, None)
    return StreamingADCProfile(
        channels=tuple(chans),
        enabled=tuple(enabled),
        rate_hz=rate,
        block_samples=block,
        url=url or None,
        baudrate=r.get(dev, "device", "baudrate", int, 921_600, check=_pos),
        model=r.get(dev, "device", "model", str, "VELAB SADC-4"),
        command_timeout_s=r.get(tmo, "timeouts", "command_s", float, 1.0, check=_pos),
        data_timeout_s=r.get(tmo, "timeouts", "data_s", float, 1.0, check=_pos),
        reconnect=r.get(tmo, "timeouts", "reconnect", bool, True),
        reconnect_timeout_s=r.get(tmo, "timeouts", "reconnect_s", float, 3.0, check=_pos),
        poll_s=r.get(tmo, "timeouts", "poll_s", float, 0.05, check=lambda v: None if 0 < v <= 1 else "must be in (0, 1] s"),
        queue_blocks=r.get(rdr, "reader", "queue_blocks", int, 2000, check=_pos),
        density_kg_m3=r.get(fluid, "fluid", "density_kg_m3", float, 998.2, check=_pos),
        path=path,
    )
