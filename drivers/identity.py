"""What a device says about itself (model, firmware, serial ...): one reading for every kind of device."""

from __future__ import annotations

from velab.drivers.base import DeviceError

IDENTITY_REGISTERS = ("model_id", "module_name", "product_code", "slave_id", "firmware", "firmware_version",
                      "serial", "serial_number", "hardware_version")


def identity(driver) -> dict:
    """What a device says about itself (model, firmware, serial ...), as far as its driver can read."""
    out = {}
    try:
        if hasattr(driver, "identify"):
            got = driver.identify()
            if isinstance(got, dict):
                out.update(got)
            else:
                parts = [p.strip() for p in str(got).split(",")]
                keys = ("manufacturer", "model", "serial", "firmware")
                out.update({k: v for k, v in zip(keys, parts)} if len(parts) == 4 else {"idn": str(got)})
        regs = getattr(getattr(driver, "profile", None), "registers", {}) or {}
        for reg in IDENTITY_REGISTERS:
            if reg in regs and reg not in out:
                out[reg] = driver.read_value(reg)
    except DeviceError as exc:
        out["error"] = str(exc)
    return out
