"""A LabJack T-series device profile (``configs/devices/labjack_t7.toml``): where the device is, how it
streams, and what is wired to which input and line. Every error is one ProfileError naming file and key."""

from __future__ import annotations

import os
from dataclasses import dataclass, field

from velab.configpath import config_stem, load_config
from velab.drivers.base import LoopCalibration, ProfileError
from velab.drivers.labjack_stream import MAX_SAMPLES_PER_PACKET, T7_RANGES
from velab.tomlschema import Key, Reader, above, within

MODELS = {"T7": 7, "T4": 4}  # model -> PRODUCT_ID (ljm_constants.json: "7 for a T7 / T7-Pro")

_TOP = {
    "kind": Key(str), "model": Key(str, choices=tuple(MODELS)), "description": Key(str, False, ""),
    "name": Key(str, False, None),
    "host": Key(str, False, "127.0.0.1"), "port": Key(int, False, 502, within(1, 65535)),
    "stream_port": Key(int, False, 702, within(1, 65535)), "unit": Key(int, False, 1, within(0, 247)),
    "calibration": Key(str, False, "device", choices=("device", "nominal")),
    "rate_hz": Key(float, False, 2000.0, above(0, 100_000, "Hz")),
    "samples_per_packet": Key(int, False, 0, within(0, MAX_SAMPLES_PER_PACKET)),
    "buffer_size_bytes": Key(int, False, 0, within(0, 262144)),
    "resolution_index": Key(int, False, 0, within(0, 8)), "settling_us": Key(float, False, 0.0, within(0, 4400, "us")),
    "max_sample_rate_hz": Key(float, False, 100_000.0, above(0, 1e6, "Hz")),
    "timeouts": Key(dict, False, {}), "digital": Key(dict, False, {}), "channels": Key(dict),
}
_TIMEOUTS = {"command_s": Key(float, False, 0.5, above(0, 60, "s")), "retries": Key(int, False, 2, within(0, 20)),
             "data_s": Key(float, False, 1.0, above(0, 600, "s"))}
_DIGITAL = {"valve_trigger": Key(int, False, None, within(0, 7)), "active_high": Key(bool, False, True)}
_CHANNEL = {
    "ain": Key(int, check=within(0, 13)), "range": Key(float, False, 10.0, choices=tuple(T7_RANGES)),
    "shunt_ohm": Key(float, False, None, above(0, 1e6, "ohm")),
    "signal_lo": Key(float), "signal_hi": Key(float), "value_lo": Key(float), "value_hi": Key(float),
    "units": Key(str, False, ""), "zero_offset": Key(float, False, 0.0), "range_margin": Key(float, False, 0.0,
                                                                                          within(0, 1)),
}


@dataclass(frozen=True)
class LJChannel:
    """One analogue input: AIN ``ain`` on its range; a current loop through ``shunt_ohm`` (signal in mA,
    NE43 limits) or a voltage (signal in V); the calibration from signal to engineering units."""

    name: str
    ain: int
    range: float
    shunt_ohm: float | None
    calibration: LoopCalibration

    @property
    def gain_index(self) -> int:
        return T7_RANGES[self.range]

    def signal(self, volts):
        """Terminal volts -> the loop's signal: mA through the shunt, else volts."""
        return volts if self.shunt_ohm is None else volts / self.shunt_ohm * 1000.0


@dataclass(frozen=True)
class LabJackProfile:
    name: str
    model: str
    host: str
    port: int
    stream_port: int
    unit: int
    calibration: str
    rate_hz: float
    samples_per_packet: int  # 0: chosen from the rate (about 20 packets/s)
    buffer_size_bytes: int
    resolution_index: int
    settling_us: float
    max_sample_rate_hz: float
    command_s: float
    retries: int
    data_s: float
    valve_trigger: int | None
    active_high: bool
    channels: tuple[LJChannel, ...] = field(default_factory=tuple)
    path: str = ""

    @property
    def product_id(self) -> int:
        return MODELS[self.model]

    def channel(self, key) -> LJChannel:
        for c in self.channels:
            if key == c.name or key == c.ain:
                return c
        raise KeyError(f"{self.path or self.name}: no channel {key!r} (have {', '.join(c.name for c in self.channels)})")


def profile_from_dict(doc: dict, path: str = "<labjack profile>", overrides: dict | None = None) -> LabJackProfile:
    """The profile of a parsed TOML document; ``overrides`` (a bench's [devices.X.channels.NAME] keys) merged."""
    r = Reader(path, doc, error=ProfileError)
    top = r.read(doc, "", _TOP)
    t = r.read(top["timeouts"], "[timeouts] ", _TIMEOUTS)
    dig = r.read(top["digital"], "[digital] ", _DIGITAL)
    chans, used = [], {}
    for name, raw in top["channels"].items():
        where = f"[channels.{name}] "
        if not isinstance(raw, dict):
            raise r.fail(where, f"must be a table, got {type(raw).__name__}")
        bench = (overrides or {}).get(name)
        if bench is not None and not isinstance(bench, dict):
            raise r.fail(f"[channels.{name}] (bench)", "must be a table")
        table = r.read({**raw, **(bench or {})}, where if bench is None else f"{where}(with the bench's keys) ",
                       _CHANNEL)
        if table["ain"] in used:
            raise r.fail(f"{where}ain", f"AIN{table['ain']} is also channel {used[table['ain']]!r}")
        used[table["ain"]] = name
        if table["signal_hi"] <= table["signal_lo"]:
            raise r.fail(f"{where}signal_hi", "must be above signal_lo")
        loop = table["shunt_ohm"] is not None
        cal = LoopCalibration(table["signal_lo"], table["signal_hi"], table["value_lo"], table["value_hi"],
                              units=table["units"], signal_units="mA" if loop else "V",
                              zero_offset=table["zero_offset"], open_loop_below=3.6 if loop else None,
                              range_margin=table["range_margin"])
        if loop and table["signal_hi"] * table["shunt_ohm"] / 1000.0 > table["range"]:
            raise r.fail(f"{where}shunt_ohm", f"{table['signal_hi']:g} mA through {table['shunt_ohm']:g} ohm is beyond "
                                              f"the +-{table['range']:g} V range")
        chans.append(LJChannel(name, table["ain"], table["range"], table["shunt_ohm"], cal))
    if not chans:
        raise r.fail("[channels]", "no channels")
    if overrides:
        unknown = sorted(set(overrides) - set(top["channels"]))
        if unknown:
            raise r.fail(f"[channels.{unknown[0]}]", "no such channel in the profile")
    return LabJackProfile(
        name=top["name"] or config_stem(path), model=top["model"], host=top["host"], port=top["port"],
        stream_port=top["stream_port"], unit=top["unit"], calibration=top["calibration"], rate_hz=top["rate_hz"],
        samples_per_packet=top["samples_per_packet"], buffer_size_bytes=top["buffer_size_bytes"],
        resolution_index=top["resolution_index"], settling_us=top["settling_us"],
        max_sample_rate_hz=top["max_sample_rate_hz"], command_s=t["command_s"], retries=t["retries"],
        data_s=t["data_s"], valve_trigger=dig["valve_trigger"], active_high=dig["active_high"],
        channels=tuple(chans), path=str(path))


def load_profile(name_or_path: str | os.PathLike | LabJackProfile = "labjack_t7",
                 overrides: dict | None = None) -> LabJackProfile:
    """A profile by short name (``devices/<name>.toml`` along the config search path) or by path."""
    if isinstance(name_or_path, LabJackProfile):
        return name_or_path
    path, doc = load_config("devices", name_or_path, error=ProfileError)
    return profile_from_dict(doc, str(path), overrides)
