"""The catalogue's columns, declared once: the Archive tab's table (velab.gui.catalogue_table) and the
text table of ``velab runs`` (velab.catalogue.query.table) are both made from :data:`COLUMNS`.

Each :class:`Column` names its sort key (velab.catalogue.query.SORT_KEYS), its header and cell text in
the window (with the widest text it shows in practice: the window opens the column that wide), and its
header, width and cell in the text table (a column without a window header is the text table's only, one
without a text width the window's only). Standard library only.
"""

from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass
from typing import Callable


def num_text(v, fmt: str) -> str:
    """A number as ``fmt``, "" for anything else (None, NaN, a bool)."""
    return format(v, fmt) if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) else ""


def start_text(row: dict) -> str:
    """The run's start, date and time to the second, in the time zone it was recorded in."""
    s = row.get("start_time")
    if not s:
        return ""
    try:
        return _dt.datetime.fromisoformat(s).strftime("%Y-%m-%d %H:%M:%S")
    except ValueError:
        return str(s)[:19].replace("T", " ")


def when_text(row: dict) -> str:
    """The run's start to the minute (the text table)."""
    s = row.get("start_time")
    if s:
        try:
            return _dt.datetime.fromisoformat(s).strftime("%Y-%m-%d %H:%M")
        except ValueError:
            return s[:16]
    return ""


def wave_speed_text(row: dict) -> str:
    a, se = row.get("wave_speed_m_s"), row.get("wave_speed_se_m_s")
    if not isinstance(a, (int, float)):
        return ""
    return f"{a:.1f} ± {se:.1f}" if isinstance(se, (int, float)) else f"{a:.1f}"


def who_text(row: dict) -> str:
    return " / ".join(x for x in (row.get("title"), row.get("operator"), row.get("specimen")) if x)


def status_text(row: dict) -> str:
    flags = ",".join(row.get("flags") or [])
    return f"{row.get('status')} [{flags}]" if flags else str(row.get("status"))


def _field(name: str) -> Callable[[dict], str]:
    return lambda r: r.get(name) or ""


@dataclass(frozen=True)
class Column:
    sort: str  # the SORT_KEYS name it sorts by
    header: str | None  # the window's header (None: not in the window)
    cell: Callable[[dict], str]
    widest: str = ""  # the widest text the window shows in practice ("": as wide as its rows need)
    text_header: str | None = None  # the text table's header (None: the window's)
    text_width: int = 0  # the text table's width (0: not in the text table)
    text_cell: Callable[[dict], str] | None = None  # the text table's cell (None: the window's)


COLUMNS = (
    Column("start", "start", start_text, "2026-11-21 08:00:00", text_width=16, text_cell=when_text),
    Column("status", "status", status_text, "completed-with-faults", text_width=24),
    Column("best", "best", _field("best_model"), "S1r", text_width=4),
    Column("wave-speed", "a m/s ± SE", wave_speed_text, "352.12 ± 0.35", text_width=13),
    Column("q0", "Q0 l/s", lambda r: num_text(r.get("measured_flow_l_s") or r.get("steady_flow_l_s"), ".3f"), "3.600",
           text_width=6),
    Column("beta", "β 1/s", lambda r: num_text(r.get("beta_per_s"), "g"), "10.5", text_header="beta", text_width=5),
    Column("rate", "rate Hz", lambda r: num_text(r.get("sample_rate_hz"), "g"), "10000", text_header="rate",
           text_width=6),
    Column("duration", "dur s", lambda r: num_text(r.get("duration_s"), ".1f"), "120.0", text_width=6),
    Column("fits", "fits", lambda r: str(r.get("n_fits") or 0) if r.get("kind") == "run" else "", "fits",
           text_width=4),
    Column("rig", "rig", _field("rig"), "perugia", text_width=14),
    Column("title", None, who_text, text_header="title / operator / specimen", text_width=28),
    Column("title", "title", _field("title"), "closure 3, material A"),
    Column("operator", "operator", _field("operator"), "operator"),
    Column("specimen", "specimen", _field("specimen"), "specimen"),
    Column("path", "file", lambda r: r["path"].rsplit("/", 1)[-1]),
)
WINDOW_COLUMNS = tuple(c for c in COLUMNS if c.header is not None)
TEXT_COLUMNS = tuple(c for c in COLUMNS if c.text_width)
