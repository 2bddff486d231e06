"""A DATAQ DI-series DAQ as a bench device: ``[devices.X] kind = "dataq"``.

``open_dataq`` is the factory velab.drivers.bench registers for that kind (``register_driver("dataq",
open_dataq)``; the bench imports this module, never the other way round)."""

from __future__ import annotations

from dataclasses import replace

from velab.drivers.base import ProfileError
from velab.drivers.dataq import DataqDAQ
from velab.drivers.dataq_profile import load_profile

# bench key -> profile field (the timeouts as in the profile's [timeouts] table)
_BENCH_OVERRIDES = {"rate_hz": "rate_hz", "baudrate": "baudrate", "packet_size": "packet_size",
                    "command_s": "command_timeout_s", "data_s": "data_timeout_s", "reconnect": "reconnect",
                    "reconnect_s": "reconnect_timeout_s"}
_BENCH_KEYS = {"url", "port", "name", *_BENCH_OVERRIDES}


def open_dataq(dev, connect: bool = True) -> DataqDAQ:
    """``[devices.X] kind = "dataq"``: ``url`` (or ``port``) = a port path or pyserial URL; ``profile`` names the
    device profile (default dataq_di2108); optional ``rate_hz``, ``baudrate``, ``packet_size``, ``command_s``,
    ``data_s``, ``reconnect``, ``reconnect_s`` override it."""
    unknown = sorted(set(dev.settings) - _BENCH_KEYS)
    if unknown:
        raise ProfileError(f"[devices.{dev.name}]: unknown key {unknown[0]!r} (known: {', '.join(sorted(_BENCH_KEYS))})")
    prof = load_profile(dev.profile or "dataq_di2108")
    over = {}
    url = dev.settings.get("url") or dev.settings.get("port")
    if url:
        over["url"] = str(url)
    for k, field in _BENCH_OVERRIDES.items():
        if k in dev.settings:
            v, kind = dev.settings[k], type(getattr(prof, field))
            if isinstance(v, bool) != (kind is bool) or not isinstance(v, (int, float)):
                raise ProfileError(f"[devices.{dev.name}] {k}: {v!r} is not a {'boolean' if kind is bool else 'number'}")
            over[field] = kind(v)
    prof = replace(prof, **over)
    lo, hi = prof.spec.rate_bounds(len(prof.enabled))
    if not lo <= prof.rate_hz <= hi:
        raise ProfileError(f"[devices.{dev.name}] rate_hz: {prof.rate_hz:g} is outside {lo:.4g}..{hi:.6g} Hz for the "
                           f"{prof.model} with {len(prof.enabled)} channel(s)")
    if not -1 <= prof.packet_size <= 7:
        raise ProfileError(f"[devices.{dev.name}] packet_size: must be 0..7 or -1 (auto)")
    if not prof.url:
        raise ProfileError(f"[devices.{dev.name}] url: missing (a port path such as /dev/ttyACM0, or socket://host:port)")
    daq = DataqDAQ(prof.url, prof, name=str(dev.settings.get("name", dev.name)))
    if connect:
        daq.open()
    return daq
