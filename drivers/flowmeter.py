"""Electromagnetic flowmeter over Modbus RTU (SITRANS F M MAG 6000 style map).

    fm = Flowmeter(open_bus({"transport": "rtu", "port": "/dev/ttyUSB0", "unit": 2}))
    fm.read_flow()        # Reading(value=0.00364, units="m3/s", quality=OK ...)
    fm.read_all()         # flow, totalizer1, totalizer2 in one block read + alarms

Quality: NaN -> NAN; any alarm bit (named or not: an unnamed bit is "bit N") -> FAULT; outside the profile's [min, max] ->
OVER/UNDER_RANGE; a non-zero value that has not changed for ``stale_after_s`` -> STALE
(the meter refreshes at 2 Hz with noise, so a frozen value means a stuck sensor). Zero
flow is the exception: with the valve closed (or below the meter's low-flow cut-off,
``[timing] low_flow_cutoff_m3_s``, default 0) the meter shows a constant 0, which is a
reading, not a stuck sensor.
"""

from __future__ import annotations

from dataclasses import replace

from velab.drivers.base import Quality, Reading
from velab.drivers.modbus_device import ModbusDevice


class Flowmeter(ModbusDevice):
    kind = "flowmeter"
    default_profile = "sitrans_mag6000"

    def __init__(self, bus, profile=None, **kw):
        super().__init__(bus, profile, **kw)
        timing = self.profile.section("timing", {})
        self.update_period_s = float(timing.get("update_period_s", 0.5))
        self.stale_after_s = float(timing.get("stale_after_s", 2.0))
        self.low_flow_cutoff_m3_s = float(timing.get("low_flow_cutoff_m3_s", 0.0))
        self._last_value: float | None = None
        self._last_change: float | None = None

    def read_alarms(self) -> list[str]:
        spec = self.profile.reg("alarms")
        return spec.bit_names(int(spec.to_value(self._read_regs(spec))))

    def _qualify(self, r: Reading, alarms: list[str]) -> Reading:
        if r.quality is Quality.NAN:
            return r
        if alarms:
            return replace(r, quality=Quality.FAULT)
        if r.quality is Quality.OK:
            if abs(r.value) <= self.low_flow_cutoff_m3_s:
                # no flow: a constant 0 is expected (closed valve, low-flow cut-off), never "stale";
                # the stuck-sensor clock restarts when the flow comes back
                self._last_value, self._last_change = r.value, r.timestamp_s
                return r
            if self._last_value is None or r.value != self._last_value:
                self._last_value, self._last_change = r.value, r.timestamp_s
            elif r.timestamp_s - self._last_change > self.stale_after_s:
                return replace(r, quality=Quality.STALE)
        return r

    def read_flow(self) -> Reading:
        """Volume flow (m3/s) with its quality (alarms read in a second request)."""
        r = self.read("flow")
        return self._qualify(r, self.read_alarms())

    def read_totalizer(self, n: int = 1) -> Reading:
        if n not in (1, 2):
            raise ValueError("totalizer must be 1 or 2")
        return self.read(f"totalizer{n}")

    def read_all(self) -> dict[str, Reading]:
        """flow, totalizer1, totalizer2 from one block read (3002..3021), plus the alarm word."""
        flow = self.profile.reg("flow")
        t2 = self.profile.reg("totalizer2")
        start, end = flow.address, t2.address + t2.count
        regs = self._bus_read("holding", start, end - start)
        ts = self.clock()
        out = {}
        for name in ("flow", "totalizer1", "totalizer2"):
            s = self.profile.reg(name)
            out[name] = self._reading(s, regs[s.address - start: s.address - start + s.count], ts)
        alarms = self.read_alarms()
        out["flow"] = self._qualify(out["flow"], alarms)
        return out

    def identify(self) -> dict:
        return {"product_code": int(self.read_value("product_code")), "slave_id": int(self.read_value("slave_id"))}
