"""Import archived records (CSV) from other acquisition systems into run files.

The CSV has a header row, then one sample per row: a time column in seconds and
a pressure column, either pressure head in m or gauge pressure in Pa, kPa or
bar (converted with rho g of the rig's fluid). Every malformed row is reported
with its line number.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from velab.errors import DataError
from velab.inputfiles import check_input_file

PRESSURE_UNITS = {"m": None, "Pa": 1.0, "kPa": 1e3, "bar": 1e5}
MIN_SAMPLES = 10

if TYPE_CHECKING:
    import numpy as np

    from velab.config import Rig
# A CSV is parsed into Python lists: refuse a file past this size (about 10 million rows)
# before reading it, rather than exhaust memory on a wrong path.
MAX_CSV_BYTES = 256 << 20


@dataclass(frozen=True)
class CsvRecord:
    time_s: np.ndarray  # as in the file
    head_m: np.ndarray  # pressure head at the transducer
    time_column: str
    value_column: str
    units: str
    sample_rate_hz: float
    valve_position_pct: np.ndarray | None = None  # the valve position column (% open), if named
    valve_column: str = ""


def _pick(header: list[str], wanted: str | None, default_index: int, path: Path, what: str) -> int:
    if wanted is None:
        if default_index >= len(header):
            raise DataError(f"{path}: line 1: expected at least 2 columns (time and pressure), found {len(header)}")
        return default_index
    if wanted in header:
        return header.index(wanted)
    raise DataError(f"{path}: line 1: no {what} column {wanted!r} (columns: {', '.join(header)})")


def read_csv_record(
    path: str | Path,
    rig: Rig,
    *,
    units: str = "m",
    time_column: str | None = None,
    value_column: str | None = None,
    valve_column: str | None = None,
    uneven_tolerance: float = 0.01,
) -> CsvRecord:
    """Parse and validate a CSV record; raises DataError naming the line."""
    import numpy as np  # here, so that `velab --help` (which reads PRESSURE_UNITS) stays light

    from velab.config import GRAVITY_M_S2

    path = Path(path)
    if units not in PRESSURE_UNITS:
        raise DataError(f"--units: must be one of {', '.join(PRESSURE_UNITS)}, got {units!r}")
    check_input_file(path, "CSV file", MAX_CSV_BYTES)
    try:
        fh = open(path, newline="", encoding="utf-8-sig")
    except OSError as exc:
        raise DataError(f"{path}: cannot read: {exc.strerror or exc}") from None
    with fh:
        try:
            sample = fh.read(4096)
        except UnicodeDecodeError:
            raise DataError(f"{path}: not a text (UTF-8) CSV file") from None
        fh.seek(0)
        if not sample.strip():
            raise DataError(f"{path}: empty file")
        try:
            dialect = csv.Sniffer().sniff(sample, delimiters=",;\t ")
        except csv.Error:
            dialect = csv.excel
        reader = csv.reader(fh, dialect)
        try:
            header = [h.strip() for h in next(reader)]
            if all(_is_number(h) for h in header if h):
                raise DataError(f"{path}: line 1: expected a header row (column names), found numbers")
            ti = _pick(header, time_column, 0, path, "time")
            vi = _pick(header, value_column, 1, path, "pressure")
            pi = None if valve_column is None else _pick(header, valve_column, -1, path, "valve position")
            times, values, positions = [], [], []
            for row in reader:
                line = reader.line_num
                if not row or all(not c.strip() for c in row):
                    continue
                if len(row) <= max(ti, vi, -1 if pi is None else pi):
                    raise DataError(f"{path}: line {line}: expected {len(header)} columns, found {len(row)}")
                t = _number(row[ti], path, line, header[ti])
                v = _number(row[vi], path, line, header[vi])
                times.append(t)
                values.append(v)
                if pi is not None:
                    p = _number(row[pi], path, line, header[pi])
                    if not -1.0 <= p <= 101.0:  # a little beyond 0..100: feedback calibration
                        raise DataError(f"{path}: line {line}: column {header[pi]!r}: valve position {p:g} is not "
                                        "a percentage open (0..100)")
                    positions.append(min(max(p, 0.0), 100.0))
        except UnicodeDecodeError:
            raise DataError(f"{path}: not a text (UTF-8) CSV file") from None
        except csv.Error as exc:
            raise DataError(f"{path}: line {reader.line_num}: {exc}") from None
    if len(times) < MIN_SAMPLES:
        raise DataError(f"{path}: too few samples ({len(times)}; at least {MIN_SAMPLES} needed)")
    t = np.asarray(times)
    v = np.asarray(values)
    dt = np.diff(t)
    # data lines start at 2 (line 1 is the header); blank lines are rare enough to ignore here
    bad = np.nonzero(dt <= 0)[0]
    if bad.size:
        i = int(bad[0]) + 1
        raise DataError(f"{path}: line {i + 2}: time {t[i]:g} s does not increase (previous {t[i - 1]:g} s)")
    step = float(np.median(dt))
    off = np.nonzero(np.abs(dt - step) > uneven_tolerance * step)[0]
    if off.size:
        i = int(off[0]) + 1
        raise DataError(
            f"{path}: line {i + 2}: uneven sampling, time step {dt[i - 1]:g} s differs from the median "
            f"{step:g} s by more than {uneven_tolerance:.0%}"
        )
    factor = PRESSURE_UNITS[units]
    head = v if factor is None else v * factor / (rig.fluid.density_kg_m3 * GRAVITY_M_S2)
    pos = np.asarray(positions) if pi is not None else None
    return CsvRecord(t, head, header[ti], header[vi], units, 1.0 / step, pos, header[pi] if pi is not None else "")


def _is_number(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


def _number(text: str, path: Path, line: int, column: str) -> float:
    try:
        v = float(text.strip())
    except ValueError:
        raise DataError(f"{path}: line {line}: column {column!r}: not a number: {text.strip()!r}") from None
    if not math.isfinite(v):
        raise DataError(f"{path}: line {line}: column {column!r}: {text.strip()} is not a finite number")
    return v
