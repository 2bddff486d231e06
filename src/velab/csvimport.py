"""Import archived records (CSV) from other acquisition systems into run files.

The CSV has a header row, then one sample per row: a time column in seconds and
a pressure column, either pressure head in m or gauge pressure in Pa, kPa or
bar (converted with rho g of the rig's fluid). Every malformed row is reported
with its line number.

A rig with several transducers (``[[transducers]]``) takes one pressure column per
transducer: the column named as the transducer, or the one ``head_columns`` maps it to
(``velab import --head-column NAME=COLUMN``). The head channel's transducer
(``Rig.head_section``, the valve's) gives ``head_m``, the others ``section_heads``.
"""

from __future__ import annotations

import csv
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from velab import bounds
from velab.errors import DataError
from velab.inputfiles import check_input_file

PRESSURE_UNITS = {"m": None, "Pa": 1.0, "kPa": 1e3, "bar": 1e5}
MIN_SAMPLES = 10

if TYPE_CHECKING:
    import numpy as np

    from velab.rig import Rig
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
    # a rig with several transducers: the heads of those other than the head channel's, by transducer name,
    # and every transducer's column
    section_heads: dict = field(default_factory=dict)
    section_columns: dict = field(default_factory=dict)


def head_columns_for(rig: Rig, value_column: str | None, head_columns: dict | None) -> dict[str, str | None]:
    """Transducer name -> its CSV column (None: the default, the second column) for ``rig``. One transducer:
    ``value_column`` or its ``head_columns`` entry. Several: each its ``head_columns`` entry, else the column
    named as the transducer. DataError (one line) for names the rig has not, or --value-column with several."""
    sections = rig.sections
    names = [x.name for x in sections]
    head_columns = dict(head_columns or {})
    unknown = [n for n in head_columns if n not in names]
    if unknown:
        raise DataError(f"--head-column {unknown[0]}=...: the rig {rig.name} has no transducer {unknown[0]!r} "
                        f"(its transducers: {', '.join(names)})")
    if len(sections) == 1:
        if value_column is not None and head_columns:
            raise DataError("give --value-column or --head-column, not both")
        return {names[0]: head_columns.get(names[0], value_column)}
    if value_column is not None:
        raise DataError(f"--value-column: the rig {rig.name} has {len(names)} transducers ({', '.join(names)}): "
                        f"name the columns after them or give --head-column NAME=COLUMN for each")
    return {n: head_columns.get(n, n) for n in names}


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
    head_columns: dict[str, str] | None = None,
    uneven_tolerance: float = 0.01,
) -> CsvRecord:
    """Parse and validate a CSV record; raises DataError naming the line. ``head_columns``: transducer name ->
    column, for a rig with several transducers (:func:`head_columns_for`)."""
    import numpy as np  # here, so that `velab --help` (which reads PRESSURE_UNITS) stays light

    from velab.rig import GRAVITY_M_S2

    path = Path(path)
    wanted = head_columns_for(rig, value_column, head_columns)
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
        if "\0" in sample:
            raise DataError(f"{path}: line {sample[:sample.index(chr(0))].count(chr(10)) + 1}: a NUL byte: not a "
                            "text CSV file")
        try:
            dialect = csv.Sniffer().sniff(sample, delimiters=",;\t ")
        except csv.Error:
            dialect = csv.excel
        reader = csv.reader(fh, dialect)
        try:
            header = [h.strip() for h in next(reader)]
            if all(_is_number(h) for h in header if h):
                raise DataError(f"{path}: line 1: expected a header row (column names), found numbers")
            named = [h for h in header if h]
            twice = sorted({h for h in named if named.count(h) > 1})
            if twice:
                raise DataError(f"{path}: line 1: column {twice[0]!r} named more than once (each column needs its "
                                "own name)")
            ti = _pick(header, time_column, 0, path, "time")
            what = "pressure" if len(wanted) == 1 else "pressure (transducer {})"
            his = {n: _pick(header, c, 1, path, what.format(repr(n))) for n, c in wanted.items()}
            pi = None if valve_column is None else _pick(header, valve_column, -1, path, "valve position")
            times, positions = [], []
            values = {n: [] for n in his}
            last = max([ti, -1 if pi is None else pi, *his.values()])
            for row in reader:
                line = reader.line_num
                if not row or all(not c.strip() for c in row):
                    continue
                if any("\0" in c for c in row):
                    raise DataError(f"{path}: line {line}: a NUL byte: not a text CSV file")
                if len(row) != len(header):
                    comma = _decimal_comma(row, header, dialect.delimiter)
                    raise DataError(f"{path}: line {line}: expected {len(header)} columns, found {len(row)}"
                                    + (f"; {comma}" if comma else ""))
                if len(times) >= bounds.MAX_SAMPLES:
                    raise DataError(f"{path}: line {line}: more than the {bounds.MAX_SAMPLES:,} samples of a record")
                t = _number(row[ti], path, line, header[ti])
                times.append(t)
                for n, i in his.items():
                    values[n].append(_number(row[i], path, line, header[i]))
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
    dt = np.diff(t)
    # data lines start at 2 (line 1 is the header); blank lines are rare enough to ignore here
    bad = np.nonzero(dt <= 0)[0]
    if bad.size:
        i = int(bad[0]) + 1
        raise DataError(f"{path}: line {i + 2}: time {t[i]:g} s does not increase (previous {t[i - 1]:g} s)")
    step = float(np.median(dt))
    if not bounds.SAMPLE_RATE_HZ.contains(1.0 / step):
        raise DataError(f"{path}: time step {step:g} s ({1.0 / step:g} Hz): the sampling rate "
                        f"{bounds.SAMPLE_RATE_HZ(1.0 / step)}; is the time column in seconds?")
    off = np.nonzero(np.abs(dt - step) > uneven_tolerance * step)[0]
    if off.size:
        i = int(off[0]) + 1
        raise DataError(
            f"{path}: line {i + 2}: uneven sampling, time step {dt[i - 1]:g} s differs from the median "
            f"{step:g} s by more than {uneven_tolerance:.0%}"
        )
    factor = PRESSURE_UNITS[units]
    heads = {n: np.asarray(v) if factor is None else np.asarray(v) * factor / (rig.fluid.density_kg_m3 * GRAVITY_M_S2)
             for n, v in values.items()}
    for n, h in heads.items():
        _check_head_range(path, rig, header[his[n]], units, np.asarray(values[n], dtype=float), h)
    main = rig.head_section.name
    pos = np.asarray(positions) if pi is not None else None
    others = {n: h for n, h in heads.items() if n != main} if len(heads) > 1 else {}
    return CsvRecord(t, heads[main], header[ti], header[his[main]], units, 1.0 / step, pos,
                     header[pi] if pi is not None else "", section_heads=others,
                     section_columns={n: header[i] for n, i in his.items()} if len(heads) > 1 else {})


def _check_head_range(path: Path, rig: Rig, column: str, units: str, raw, head) -> None:
    """Refuse heads the rig's transducer cannot read (velab.bounds.head_range_m: the vacuum to 1.5 x its full
    scale), naming the unit the column is likely in: a kPa column read as metres is ten times too high."""
    import numpy as np

    lo, hi = bounds.head_range_m(rig)
    with np.errstate(over="ignore", invalid="ignore"):
        bad = ~((head >= lo) & (head <= hi))
    if not bad.any():
        return
    i = int(np.argmax(bad))
    rho_g = rig.fluid.density_kg_m3 * bounds.GRAVITY_M_S2
    with np.errstate(over="ignore", invalid="ignore"):
        median = float(np.median(raw))
    fits = []
    for u, f in PRESSURE_UNITS.items():
        with np.errstate(over="ignore", invalid="ignore"):
            h = raw if f is None else raw * f / rho_g
            ok = bool(np.all((h >= lo) & (h <= hi)))
        if u != units and ok:
            fits.append((abs(math.log(max(abs(median if f is None else median * f / rho_g), 1e-9)
                                      / max(rig.steady_head_m, 1e-9))), u, median if f is None else median * f / rho_g))
    hint = ""
    if fits:
        _, u, steady = min(fits)
        hint = f"; the column looks like {u} (--units {u}: median head {steady:.3g} m, the rig's steady {rig.steady_head_m:.3g} m)"
    shown = float(head[i])
    raise DataError(f"{path}: line {i + 2}: column {column!r}: head {shown:.4g} m (read as {units}) is beyond what the "
                    f"rig's transducer reads ({lo:g} .. {hi:.3g} m: the vacuum to {bounds.OVER_RANGE:g} x its "
                    f"{rig.transducer.full_scale_pa / 1e5:g} bar full scale){hint}")


_DECIMAL_COMMA = re.compile(r"^\s*[+-]?\d+,\d+\s*$")


def _decimal_comma(row: list[str], header: list[str], delimiter: str) -> str:
    """The hint for a row that a decimal comma split ("0,001" read as two fields), or ""."""
    if delimiter == "," and len(row) == 2 * len(header) and all(c.strip().lstrip("+-").isdigit() for c in row):
        return 'decimal commas? ("0,001" splits into two fields: velab reads a decimal point, "0.001")'
    return ""


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
        comma = " (a decimal comma: velab reads a decimal point, 0.001)" if _DECIMAL_COMMA.match(text) else ""
        raise DataError(f"{path}: line {line}: column {column!r}: not a number: {text.strip()!r}{comma}") from None
    if not math.isfinite(v):
        raise DataError(f"{path}: line {line}: column {column!r}: {text.strip()} is not a finite number")
    return v
