"""Modbus register data types and word orders (pure functions, no I/O).

uint16, int16, uint32, int32, float32, uint64, float64 in ABCD (big endian), CDAB
(word swapped), BADC (byte swapped) and DCBA (little endian).
"""

from __future__ import annotations

import enum
import struct
from typing import Sequence


class WordOrder(str, enum.Enum):
    """Order of the bytes of a multi-register value, A = most significant byte."""

    ABCD = "ABCD"  # big endian (Modbus default; pymodbus word_order="big")
    CDAB = "CDAB"  # low word first, bytes big endian inside a word (E+H "1-0-3-2")
    BADC = "BADC"  # high word first, bytes swapped inside each word
    DCBA = "DCBA"  # little endian

    @property
    def word_swap(self) -> bool:
        return self in (WordOrder.CDAB, WordOrder.DCBA)

    @property
    def byte_swap(self) -> bool:
        return self in (WordOrder.BADC, WordOrder.DCBA)


_TYPES = {  # name -> (struct code, registers)
    "uint16": ("H", 1),
    "int16": ("h", 1),
    "uint32": ("I", 2),
    "int32": ("i", 2),
    "float32": ("f", 2),
    "uint64": ("Q", 4),
    "float64": ("d", 4),
}
DATA_TYPES = tuple(_TYPES)


def register_count(dtype: str) -> int:
    try:
        return _TYPES[dtype][1]
    except KeyError:
        raise ValueError(f"unknown data type {dtype!r} (known: {', '.join(_TYPES)})") from None


def _reorder(words: list[int], order: WordOrder) -> list[int]:
    if order.byte_swap:
        words = [((w & 0xFF) << 8) | (w >> 8) for w in words]
    if order.word_swap:
        words = words[::-1]
    return words


def decode_registers(regs: Sequence[int], dtype: str, order: WordOrder | str = WordOrder.ABCD) -> int | float:
    """Registers (as on the wire, first address first) -> Python value."""
    code, n = _TYPES[dtype] if dtype in _TYPES else (None, register_count(dtype))
    if len(regs) != n:
        raise ValueError(f"{dtype} needs {n} registers, got {len(regs)}")
    words = _reorder(list(regs), WordOrder(order))  # the transform is its own inverse
    return struct.unpack(">" + code, struct.pack(f">{n}H", *words))[0]


def encode_value(value: int | float, dtype: str, order: WordOrder | str = WordOrder.ABCD) -> list[int]:
    """Python value -> registers in wire order."""
    code, n = _TYPES[dtype] if dtype in _TYPES else (None, register_count(dtype))
    if code in "HhIiQ":
        value = int(value)
    try:
        words = list(struct.unpack(f">{n}H", struct.pack(">" + code, value)))
    except struct.error as exc:
        raise ValueError(f"{value!r} does not fit a {dtype}: {exc}") from None
    return _reorder(words, WordOrder(order))
