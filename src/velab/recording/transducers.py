"""The bench's channel map: every pressure transducer of the rig -> a channel of the pressure source, and
the run file's channels it is recorded in.

A rig names its transducers (``[[transducers]]``, velab.rig: ``sections``, ``head_section``); the bench says
which ADC channel each is wired to (``[recorder.transducers]``, velab.drivers.bench: transducer name ->
channel name). The valve's transducer (``rig.head_section``) is the source's first pressure channel unless
the table names it; every other transducer must be named there. A rig with one transducer needs nothing.

In the run file the valve's transducer is ``head`` (with ``pressure``, ``pressure_raw``,
``pressure_quality``), each other one the same channels with ``_NAME`` appended (``head_mid``, ...):
what ``velab synth`` writes and ``velab.runfiles.reader`` / ``velab.fitting.sections`` read
(``Rig.section_channel``).
"""

from __future__ import annotations

from dataclasses import dataclass

from velab.errors import ConfigError
from velab.rig import Rig

TABLE = "[recorder.transducers]"
# the per-transducer fast channels: the valve's transducer has them as they are, the others with "_NAME"
CHANNELS = ("head", "pressure", "pressure_raw", "pressure_quality")


@dataclass(frozen=True)
class TransducerChannel:
    """One transducer of the rig as the recorder records it."""

    name: str  # the rig's name of the transducer
    position_m: float  # its distance from the upstream reservoir
    adc_channel: str  # the pressure source's channel it is wired to
    head: str  # its head channel in the run file: "head" (the valve's) or "head_NAME"

    @property
    def at_valve(self) -> bool:
        """The valve's transducer: its head is the run's ``head`` (steady head, ceiling, trigger, fit window)."""
        return self.head == "head"

    def channel(self, base: str) -> str:
        """The run file's name of one of its channels (``CHANNELS``): ``base`` for the valve's, ``base_NAME``."""
        return base if self.at_valve else f"{base}_{self.name}"


def transducer_channels(rig: Rig, mapping: dict, where: str, pressure_channels: tuple[str, ...] | None = None,
                        source: str = "the pressure source") -> tuple[TransducerChannel, ...]:
    """Every transducer of ``rig``, the valve's first, with its channel (``mapping``: the bench's
    ``[recorder.transducers]``). ``pressure_channels``: the source's channels in Pa, its first the default
    of the valve's transducer (None: the names are checked, not the channels). ConfigError, one line naming
    ``where`` (the bench file), the table and the key, for a transducer the rig does not have, one of the
    rig's without a channel, a channel that is not one of the source's pressure channels or is taken twice."""
    names = [s.name for s in rig.sections]
    for name in mapping:
        if name not in names:
            raise ConfigError(f"{where}: {TABLE} {name}: the rig {rig.name!r} has no transducer {name!r} "
                              f"(its transducers: {', '.join(names)})")
    valve = rig.head_section
    ordered = [valve] + [s for s in rig.sections if s != valve]
    out, taken = [], {}
    for sec in ordered:
        channel = mapping.get(sec.name)
        if channel is None and sec == valve:
            channel = pressure_channels[0] if pressure_channels else None
        if channel is None and sec != valve:
            raise ConfigError(f"{where}: {TABLE}: no channel for the transducer {sec.name!r} at {sec.position_m:g} m "
                              f"of the rig {rig.name!r} (name the pressure source's channel it is wired to: "
                              f"{sec.name} = \"CHANNEL\")")
        if pressure_channels is not None and channel is not None:
            if channel not in pressure_channels:
                raise ConfigError(f"{where}: {TABLE} {sec.name}: {channel!r} is not a pressure channel (units Pa) "
                                  f"of {source} (its pressure channels: {', '.join(pressure_channels) or 'none'})")
            if channel in taken:
                raise ConfigError(f"{where}: {TABLE} {sec.name}: channel {channel!r} is taken by the transducer "
                                  f"{taken[channel]!r} (one transducer per channel)")
            taken[channel] = sec.name
        out.append(TransducerChannel(sec.name, sec.position_m, channel or "", rig.section_channel(sec)))
    _check_channel_names(out, rig, where)
    return tuple(out)


def _check_channel_names(transducers: list[TransducerChannel], rig: Rig, where: str) -> None:
    """Two transducers' channels never share a name in the run file (a transducer named "raw" would make
    ``pressure_raw`` twice)."""
    seen: dict[str, str] = {}
    for t in transducers:
        for base in CHANNELS:
            name = t.channel(base)
            if name in seen:
                raise ConfigError(f"{where}: the rig {rig.name!r}'s transducer {t.name!r} would be recorded as "
                                  f"{name!r}, a channel of the transducer {seen[name]!r}: rename it in the rig file")
            seen[name] = t.name
