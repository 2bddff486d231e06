"""Where a simulated device is served: one ``Endpoint`` per transport (a leaf module: every
simulated device kind and the bench that composes them import it)."""

from __future__ import annotations

from dataclasses import asdict, dataclass


@dataclass(frozen=True)
class Endpoint:
    device: str
    kind: str
    transport: str  # "tcp" | "rtu-socket" | "rtu-pty" | other kinds' own
    address: str  # tcp://host:port, socket://host:port, /dev/pts/N
    unit: int | None = None
    port: int | None = None
    link: str | None = None  # stable symlink to a pty path
    baudrate: int | None = None

    def to_dict(self) -> dict:
        return {k: v for k, v in asdict(self).items() if v is not None}

    def bench_settings(self) -> dict:
        """The [devices.X] connection keys that reach this endpoint."""
        if self.kind == "streaming_adc":  # a serial stream: a pyserial URL (socket://) or the pty path
            return {"url": self.address if self.transport == "socket" else (self.link or self.address)}
        if self.transport == "tcp":
            return {"transport": "tcp", "host": self.address.split("//")[1].rsplit(":", 1)[0], "port": self.port,
                    "unit": self.unit}
        return {"transport": "rtu", "port": self.link or self.address, "unit": self.unit,
                "baudrate": self.baudrate or 19200}
