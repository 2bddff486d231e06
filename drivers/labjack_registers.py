"""The LabJack T-series registers velab uses: name, Modbus address, type, access (one table).

Source: LabJack's register map ``LabJack/LJM/ljm_constants.json`` (github.com/labjack/ljm_constants, header
version 2025.12.18.A), checked entry by entry by ``tests/drivers/test_labjack_registers.py`` against an excerpt
of that file. One exception, from the T-series datasheet section 3.2.4 "Low-Level Stream": STREAM_DATATYPE
(4018) "must be written with the value 0" and "is not in ljm_constants.json" (``in_map=False``).

Indexed registers (``AIN#(0:249)``, ``FIO#(0:7)``, ``STREAM_SCANLIST_ADDRESS#(0:127)``) are one entry of the map
at the index-0 address; register ``n`` of the family is at ``address + n * words`` (the map's expansion rule:
each index takes the registers of one value of its type), built by :func:`indexed`.

Types as the map names them: UINT16, UINT32, FLOAT32 (1 or 2 Modbus registers, big endian: most significant
word first), STRING (50 bytes = 25 registers, NUL-terminated).
"""

from __future__ import annotations

from dataclasses import dataclass

WORDS = {"UINT16": 1, "UINT32": 2, "INT32": 2, "FLOAT32": 2, "STRING": 25}
STRING_BYTES = 50  # ljm_constants.json: STRING values are 50 bytes ("up to 49 characters" for the device name)


@dataclass(frozen=True)
class LJRegister:
    """One register (or the index-0 register of a family ``NAME#(lo:hi)``) of LabJack's map."""

    name: str  # as in ljm_constants.json, e.g. "AIN#(0:249)_RANGE"
    address: int
    type: str  # UINT16 | UINT32 | FLOAT32 | STRING
    access: str  # "R", "W" or "RW" (the map's readwrite)
    in_map: bool = True  # False: documented in the datasheet only (STREAM_DATATYPE)

    @property
    def words(self) -> int:
        return WORDS[self.type]

    @property
    def dtype(self) -> str:
        """velab's Modbus data type (velab.drivers.modbus_types) of a numeric register."""
        return {"UINT16": "uint16", "UINT32": "uint32", "INT32": "int32", "FLOAT32": "float32"}[self.type]

    @property
    def family(self) -> tuple[int, int] | None:
        """(first, last) index of an indexed family, None for a single register."""
        if "#(" not in self.name:
            return None
        lo, hi = self.name.split("#(", 1)[1].split(")", 1)[0].split(":")
        return int(lo), int(hi)


_TABLE = (
    # analog inputs (T-series datasheet 14.0 "Analog Inputs"; ljm tag AIN)
    LJRegister("AIN#(0:249)", 0, "FLOAT32", "R"),  # volts, command-response only while no stream runs
    LJRegister("AIN#(0:249)_RANGE", 40000, "FLOAT32", "RW"),  # T7: 10, 1, 0.1, 0.01 (+-V); 0 = default +-10 V
    LJRegister("AIN#(0:249)_NEGATIVE_CH", 41000, "UINT16", "RW"),  # 199 = single ended (GND)
    LJRegister("AIN#(0:249)_RESOLUTION_INDEX", 41500, "UINT16", "RW"),  # command-response reads; 0 = default
    # digital I/O (13.0 "Digital I/O"; tag DIO)
    LJRegister("FIO#(0:7)", 2000, "UINT16", "RW"),  # one line: a write sets it to output at that level
    LJRegister("FIO_STATE", 2500, "UINT16", "RW"),  # 8 FIO bits (upper byte: inhibits on writes)
    LJRegister("FIO_DIRECTION", 2600, "UINT16", "RW"),  # 1 = output
    LJRegister("DIO_STATE", 2800, "UINT32", "RW"),
    LJRegister("DIO_DIRECTION", 2850, "UINT32", "RW"),
    # stream (3.2 "Stream Mode", 3.2.4 "Low-Level Stream"; tag STREAM)
    LJRegister("STREAM_SCANRATE_HZ", 4002, "FLOAT32", "RW"),  # a read returns the actual scan rate
    LJRegister("STREAM_NUM_ADDRESSES", 4004, "UINT32", "RW"),
    LJRegister("STREAM_SAMPLES_PER_PACKET", 4006, "UINT32", "RW"),  # spontaneous mode only
    LJRegister("STREAM_SETTLING_US", 4008, "FLOAT32", "RW"),  # 0 = automatic
    LJRegister("STREAM_RESOLUTION_INDEX", 4010, "UINT32", "RW"),  # 0 = index 1
    LJRegister("STREAM_BUFFER_SIZE_BYTES", 4012, "UINT32", "RW"),  # power of 2; 0 = default (T7 4096)
    LJRegister("STREAM_AUTO_TARGET", 4016, "UINT32", "RW"),  # bit 0: Ethernet 702 sockets; bit 4: C-R
    LJRegister("STREAM_DATATYPE", 4018, "UINT32", "W", in_map=False),  # 3.2.4: write 0; not in the map
    LJRegister("STREAM_NUM_SCANS", 4020, "UINT32", "RW"),  # 0 = continuous (non-zero: a burst)
    LJRegister("STREAM_AUTORECOVER_DISABLE", 4028, "UINT32", "RW"),  # 1: buffer full stops the stream
    LJRegister("STREAM_SCANLIST_ADDRESS#(0:127)", 4100, "UINT32", "RW"),
    LJRegister("STREAM_ENABLE", 4990, "UINT32", "RW"),  # written last: 1 starts, 0 stops
    # identity (tag CONFIG)
    LJRegister("PRODUCT_ID", 60000, "FLOAT32", "R"),  # 4 T4, 7 T7 / T7-Pro, 8 T8
    LJRegister("HARDWARE_VERSION", 60002, "FLOAT32", "R"),
    LJRegister("FIRMWARE_VERSION", 60004, "FLOAT32", "R"),
    LJRegister("SERIAL_NUMBER", 60028, "UINT32", "R"),
    LJRegister("DEVICE_NAME_DEFAULT", 60500, "STRING", "RW"),
    # internal flash: the factory calibration constants (20.0 "Internal Flash"; tag INTFLASH)
    LJRegister("INTERNAL_FLASH_READ_POINTER", 61810, "UINT32", "RW"),
    LJRegister("INTERNAL_FLASH_READ", 61812, "UINT32", "R"),  # "read size must be an even number of registers"
)

REGISTERS: dict[str, LJRegister] = {r.name: r for r in _TABLE}


def reg(name: str) -> LJRegister:
    """A single register by its map name (``"STREAM_ENABLE"``) or a family by its base (``"AIN#(0:249)"``)."""
    try:
        return REGISTERS[name]
    except KeyError:
        raise KeyError(f"no LabJack register {name!r} in velab's table (velab.drivers.labjack_registers)") from None


def indexed(family: str, n: int) -> int:
    """The address of register ``n`` of a family: ``indexed("AIN#(0:249)_RANGE", 1) == 40002``."""
    r = reg(family)
    lo, hi = r.family
    if not lo <= n <= hi:
        raise ValueError(f"{family}: index {n} outside {lo}..{hi}")
    return r.address + n * r.words


def ain(n: int) -> int:
    return indexed("AIN#(0:249)", n)


def ain_range(n: int) -> int:
    return indexed("AIN#(0:249)_RANGE", n)


def ain_negative_ch(n: int) -> int:
    return indexed("AIN#(0:249)_NEGATIVE_CH", n)


def ain_resolution_index(n: int) -> int:
    return indexed("AIN#(0:249)_RESOLUTION_INDEX", n)


def fio(n: int) -> int:
    return indexed("FIO#(0:7)", n)


def scanlist_address(n: int) -> int:
    return indexed("STREAM_SCANLIST_ADDRESS#(0:127)", n)


# STREAM_AUTO_TARGET bits (the map's description): spontaneous packets to the Ethernet 702 sockets
AUTO_TARGET_ETHERNET = 0x01
AUTO_TARGET_USB = 0x02
AUTO_TARGET_COMMAND_RESPONSE = 0x10
STREAM_PORT = 702  # "Send to Ethernet 702 sockets"
MODBUS_PORT = 502
SINGLE_ENDED = 199  # AIN#_NEGATIVE_CH: GND

# T7 factory calibration constants in internal flash (T-series datasheet 20.0.1 "T7 Calibration Constants"):
# from this flash address, 41 big-endian float32: for each of HS gain 1/10/100/1000 then HR (T7-Pro) gain
# 1/10/100/1000, (positive slope, negative slope, binary center, offset); DAC0, DAC1 (slope, offset);
# temperature (slope, offset); I source 10 uA, 200 uA; AIN bias current.
T7_CAL_FLASH_ADDRESS = 0x3C4000
T7_CAL_FLOATS = 41

# stream status codes: ljm_constants.json "errors" (and datasheet 3.2.4 "Data Collection")
STREAM_STATUS = {
    2940: "STREAM_AUTO_RECOVER_ACTIVE",  # buffer full: new scans are discarded until it has room
    2941: "STREAM_AUTO_RECOVER_END",  # additional status = the number of scans skipped
    2942: "STREAM_SCAN_OVERLAP",  # a scan started before the previous one ended
    2943: "STREAM_AUTO_RECOVER_END_OVERFLOW",  # the skipped-scan counter overflowed: the loss is unknown
    2944: "STREAM_BURST_COMPLETE",
    2945: "STREAM_BUFFER_FULL",  # buffer full with auto-recovery disabled: stream stopped
}
STREAM_AUTO_RECOVER_ACTIVE, STREAM_AUTO_RECOVER_END, STREAM_SCAN_OVERLAP = 2940, 2941, 2942
STREAM_AUTO_RECOVER_END_OVERFLOW, STREAM_BURST_COMPLETE, STREAM_BUFFER_FULL = 2943, 2944, 2945
