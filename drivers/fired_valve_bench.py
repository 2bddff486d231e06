"""The fired valve as a bench device: ``[devices.X] kind = "fired_valve"``.

    [devices.valve]
    kind = "fired_valve"
    daq = "daq"                       # the bench device whose digital output fires the valve
    fire_line = 0                     # its digital output line
    fire_level = "high"               # "high" (energise to close) or "low"
    position_channel = "valve_position"   # the analog channel of the position potentiometer
    position_daq = "daq"              # optional: another device's channel (default: daq)
    reset_line = 1                    # optional: a line pulsed to reopen (double-acting); default: release fire_line
    closed_pct = 2.0                  # optional: the stroke's ends
    open_pct = 98.0
    stroke_timeout_s = 3.0            # fired and no stroke seen after this (host s): FAULT
    reopen_timeout_s = 10.0

``open_fired_valve(dev, connect, peers)``: ``peers(name)`` gives the driver of another bench device (opened
once, shared: the DAQ that fires the valve is the one that records the pressure).
"""

from __future__ import annotations

from velab.drivers.base import ProfileError
from velab.drivers.fired_valve import DaqLine, DaqPosition, FiredValve
from velab.tomlschema import Key, Reader, above, within

_SPEC = {
    "daq": Key(str, True, None),
    "fire_line": Key(int, False, 0, check=within(0, 31, "")),
    "fire_level": Key(str, False, "high", choices=("high", "low")),
    "position_channel": Key(str, False, "valve_position"),
    "position_daq": Key(str, False, None),
    "reset_line": Key(int, False, None, check=within(0, 31, "")),
    "closed_pct": Key(float, False, 2.0, check=within(0.0, 50.0, "%")),
    "open_pct": Key(float, False, 98.0, check=within(50.0, 100.0, "%")),
    "stroke_timeout_s": Key(float, False, 3.0, check=above(0.0, 60.0, "s")),
    "reopen_timeout_s": Key(float, False, 10.0, check=above(0.0, 600.0, "s")),
    "name": Key(str, False, None),
}


def open_fired_valve(dev, connect: bool = True, peers=None) -> FiredValve:
    where = f"[devices.{dev.name}] "
    r = Reader(None, dict(dev.settings), error=ProfileError)
    s = r.read(dict(dev.settings), where, _SPEC)
    if peers is None:
        raise ProfileError(f"{where}daq: a fired valve needs its bench's devices (open it through the bench)")
    daq = peers(s["daq"])
    pos_daq = peers(s["position_daq"]) if s["position_daq"] else daq
    for who, key in ((daq, "daq"), (pos_daq, "position_daq")):
        need = ("write_digital",) if key == "daq" else ("latest", "read_analog")
        missing = [m for m in need if not callable(getattr(who, m, None))]
        if missing:
            raise ProfileError(f"{where}{key}: {s[key] or s['daq']!r} ({type(who).__name__}) has no "
                               f"{' / '.join(missing)}: not a DAQ with digital outputs and analog inputs")
    channels = getattr(pos_daq, "channel_names", None)
    if callable(channels) and s["position_channel"] not in channels():
        raise ProfileError(f"{where}position_channel: {s['position_channel']!r} is not a channel of "
                           f"{s['position_daq'] or s['daq']!r} (have: {', '.join(channels())})")
    reset = DaqLine(daq, s["reset_line"]) if s["reset_line"] is not None else None
    return FiredValve(s["name"] or dev.name, DaqLine(daq, s["fire_line"]), DaqPosition(pos_daq, s["position_channel"]),
                      fire_level=s["fire_level"] == "high", reset_line=reset, closed_pct=s["closed_pct"],
                      open_pct=s["open_pct"], stroke_timeout_s=s["stroke_timeout_s"],
                      reopen_timeout_s=s["reopen_timeout_s"])
