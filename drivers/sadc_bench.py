"""The streaming ADC as a bench device: ``[devices.X] kind = "streaming_adc"`` (velab.drivers.bench)."""

from __future__ import annotations

from dataclasses import replace

from velab.drivers.base import ProfileError
from velab.drivers.bench import register_driver
from velab.drivers.sadc_profile import load_profile
from velab.drivers.streaming_adc import StreamingADC

# bench key -> profile field (the timeouts as in the profile's [timeouts] table)
_BENCH_OVERRIDES = {"rate_hz": "rate_hz", "block_samples": "block_samples", "baudrate": "baudrate",
                    "command_s": "command_timeout_s", "data_s": "data_timeout_s", "reconnect": "reconnect",
                    "reconnect_s": "reconnect_timeout_s"}
_BENCH_KEYS = {"url", "port", "name", *_BENCH_OVERRIDES}


def _bench_factory(dev, connect: bool = True) -> "StreamingADC":
    """``[devices.X] kind = "streaming_adc"``: ``url`` (or ``port``) = pyserial URL / path;
    optional ``rate_hz``, ``block_samples``, ``baudrate``, ``command_s``, ``data_s``, ``reconnect``,
    ``reconnect_s`` override the profile."""
    unknown = sorted(set(dev.settings) - _BENCH_KEYS)
    if unknown:
        raise ProfileError(f"[devices.{dev.name}]: unknown key {unknown[0]!r} (known: {', '.join(sorted(_BENCH_KEYS))})")
    prof = load_profile(dev.profile or "streaming_adc")
    over = {}
    url = dev.settings.get("url") or dev.settings.get("port")
    if url:
        over["url"] = str(url)
    for k, field in _BENCH_OVERRIDES.items():
        if k in dev.settings:
            try:
                over[field] = type(getattr(prof, field))(dev.settings[k])
            except (TypeError, ValueError):
                raise ProfileError(f"[devices.{dev.name}] {k}: {dev.settings[k]!r} is not a number") from None
    prof = replace(prof, **over)
    if not prof.url:
        raise ProfileError(f"[devices.{dev.name}] url: missing (a pyserial URL such as socket://host:port or a port path)")
    adc = StreamingADC(prof.url, prof, name=str(dev.settings.get("name", dev.name)))
    if connect:
        adc.open()
    return adc


register_driver("streaming_adc", _bench_factory)
