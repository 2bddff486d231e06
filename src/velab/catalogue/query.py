"""Filters, sort keys and the text and CSV forms of catalogue rows (shared by ``velab runs`` and the GUI).

Standard library only: a listing answered from the index never imports numpy or h5py.
"""

from __future__ import annotations

import csv
import datetime as _dt
import functools
import io
import json
import math
from dataclasses import dataclass

from velab.catalogue.columns import TEXT_COLUMNS, when_text

STATUSES = ("recording", "interrupted", "completed", "completed-with-faults", "stopped", "aborted", "failed",
            "synthetic", "imported", "damaged")
# velab.runfiles.layout.STATUSES and the catalogue's own: "damaged", "interrupted" (says recording, no writer: liveness)

# sort key name -> row field (the GUI's columns sort by the same fields)
SORT_KEYS = {
    "start": "start_time", "path": "path", "status": "status", "title": "title", "operator": "operator",
    "specimen": "specimen", "rig": "rig", "q0": "steady_flow_l_s", "beta": "beta_per_s", "rate": "sample_rate_hz",
    "duration": "duration_s", "best": "best_model", "wave-speed": "wave_speed_m_s", "se": "wave_speed_se_m_s",
    "fits": "n_fits", "noise": "noise_ratio",
}


def parse_when(text: str, end: bool = False) -> float:
    """``YYYY-MM-DD`` or an ISO 8601 date-time -> epoch s (local time when no offset is given).

    A bare date with ``end`` is the end of that day (``--until 2026-11-25`` includes the 25th).
    """
    s = str(text).strip()
    try:
        if len(s) == 10:
            d = _dt.datetime.combine(_dt.date.fromisoformat(s), _dt.time())
            if end:
                d += _dt.timedelta(days=1)
        else:
            d = _dt.datetime.fromisoformat(s)
    except ValueError:
        raise ValueError(f"not a date: {text!r} (use YYYY-MM-DD or YYYY-MM-DDTHH:MM[:SS][+HH:MM])") from None
    t = (d if d.tzinfo else d.astimezone()).timestamp()
    return t - 1e-6 if end and len(s) == 10 else t


Q0_TOLERANCE = 0.03  # a single --q0 value: within 3 % (a flowmeter's reading around a set steady flow)


def parse_range(text: str, tolerance: float = Q0_TOLERANCE) -> tuple[float | None, float | None]:
    """``MIN:MAX`` (either side may be empty), ``VALUE~TOL`` or ``VALUE`` (within ``tolerance`` of it) -> (lo, hi)."""
    s = str(text).strip()
    try:
        if ":" in s:
            lo_s, hi_s = (p.strip() for p in s.split(":", 1))
            lo = float(lo_s) if lo_s else None
            hi = float(hi_s) if hi_s else None
        elif "~" in s:
            v, tol = (float(p) for p in s.split("~", 1))
            if tol < 0:
                raise ValueError
            lo, hi = v - tol, v + tol
        else:
            v = float(s)
            lo, hi = v - abs(v) * tolerance, v + abs(v) * tolerance
    except ValueError:
        raise ValueError(f"not a range: {text!r} (use MIN:MAX, MIN:, :MAX, VALUE~TOL or VALUE)") from None
    if any(x is not None and not math.isfinite(x) for x in (lo, hi)):
        raise ValueError(f"not a range: {text!r} (the bounds must be finite numbers)")
    if lo is None and hi is None:
        raise ValueError(f"not a range: {text!r} (give at least one bound)")
    if lo is not None and hi is not None and lo > hi:
        raise ValueError(f"not a range: {text!r} (MIN {lo:g} is above MAX {hi:g})")
    return lo, hi


def row_flow(row: dict) -> float | None:
    """The run's steady flow Q0, l/s: the measured one where recorded, else the manoeuvre's (as the table shows)."""
    for k in ("measured_flow_l_s", "steady_flow_l_s"):
        v = row.get(k)
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v:
            return float(v)
    return None


@functools.lru_cache(maxsize=1 << 16)
def _instant(s: str) -> float | None:
    """An ISO 8601 start time -> epoch s (local time when no offset); remembered: the GUI sorts the same rows
    again at every added batch and filter change, and parsing is most of a sort by start."""
    try:
        d = _dt.datetime.fromisoformat(s)
    except ValueError:
        return None
    return (d if d.tzinfo else d.astimezone()).timestamp()


def row_time(row: dict) -> float | None:
    """When the run started (epoch s); the file's mtime for a damaged file or a run without a start time."""
    s = row.get("start_time")
    if s:
        t = _instant(s)
        if t is not None:
            return t
    m = row.get("mtime")
    return float(m) if isinstance(m, (int, float)) else None


# the row fields Filters reads (velab.catalogue.index.LIGHT keeps them, and the SORT_KEYS fields, as columns)
FILTER_FIELDS = ("kind", "status", "best_model", "rig", "start_time", "mtime", "measured_flow_l_s", "steady_flow_l_s",
                 "title", "operator", "specimen", "notes")


@dataclass
class Filters:
    """What ``velab runs`` and the Archive tab filter on; empty fields match everything."""

    status: tuple[str, ...] = ()  # any of these
    best: tuple[str, ...] = ()  # best model of the latest fit, any of these ("none": not fitted)
    rig: str = ""  # part of the rig's name, any case
    since: float | None = None  # epoch s, start time >= since
    until: float | None = None  # epoch s, start time <= until
    text: tuple[str, ...] = ()  # every word in title, operator, specimen or notes, any case
    q0: tuple[float | None, float | None] | None = None  # steady flow (l/s) range, either bound may be None

    def match(self, row: dict) -> bool:
        if self.status and row.get("status") not in self.status:
            return False
        if self.best:
            best = (row.get("best_model") or "none").lower()
            if best not in {b.lower() for b in self.best}:
                return False
        if self.rig and self.rig.lower() not in (row.get("rig") or "").lower():
            return False
        if self.since is not None or self.until is not None:
            t = row_time(row)
            if t is None or (self.since is not None and t < self.since) or (self.until is not None and t > self.until):
                return False
        if self.q0 is not None:
            q, (lo, hi) = row_flow(row), self.q0
            if q is None or (lo is not None and q < lo) or (hi is not None and q > hi):
                return False
        if self.text:
            hay = " ".join(str(row.get(k) or "") for k in ("title", "operator", "specimen", "notes")).lower()
            if not all(w.lower() in hay for w in self.text):
                return False
        return True

    def apply(self, rows: list[dict]) -> list[dict]:
        return [r for r in rows if self.match(r)]


def sort_rows(rows: list[dict], key: str = "start") -> list[dict]:
    """Rows sorted by a :data:`SORT_KEYS` name (``-name``: descending); unknown values always last."""
    desc = key.startswith("-")
    field = SORT_KEYS[key.lstrip("-")]
    known = [r for r in rows if r.get(field) not in (None, "")]
    unknown = [r for r in rows if r.get(field) in (None, "")]
    if field == "start_time":
        kf = lambda r: (row_time(r) or 0.0, r["path"])  # noqa: E731 - offsets differ: compare instants
    else:
        kf = lambda r: (r[field].lower() if isinstance(r[field], str) else r[field], r["path"])  # noqa: E731
    return sorted(known, key=kf, reverse=desc) + sorted(unknown, key=lambda r: r["path"])


# ------------------------------------------------------------------ text forms


# the text table's columns: velab.catalogue.columns (the window's table is made from the same declaration)
TABLE = tuple((c.text_header or c.header, c.text_width, c.text_cell or c.cell) for c in TEXT_COLUMNS)


def _cut(text: str, width: int) -> str:
    return text if len(text) <= width else text[:width - 1] + "…"


def table(rows: list[dict], relative_to: list[str] | None = None) -> str:
    """The text table of ``rows``: one line each, the damaged ones with their reason."""
    import os

    def rel(p: str) -> str:
        for r in relative_to or ():
            if p.startswith(r.rstrip(os.sep) + os.sep):
                return p[len(r.rstrip(os.sep)) + 1:]
        return p

    head = "  ".join(h.ljust(w) for h, w, _ in TABLE) + "  file"
    lines = [head]
    for row in rows:
        if row.get("status") == "damaged":
            lines.append(f"{when_text(row):<16}  {'damaged':<24}  {rel(row['path'])}: {row.get('reason') or ''}")
            continue
        lines.append("  ".join(_cut(str(f(row)), w).ljust(w) for _, w, f in TABLE) + "  " + rel(row["path"]))
    return "\n".join(lines)


def _csv_value(v):
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ""
    if isinstance(v, list):
        if all(isinstance(x, str) for x in v):
            return ";".join(v)
        return json.dumps(v, allow_nan=False, default=str)
    return v


def to_csv(rows: list[dict]) -> str:
    """Every column of the rows (:data:`velab.catalogue.rows.COLUMNS`); lists as ``a;b``, elements as JSON."""
    from velab.catalogue.rows import COLUMNS

    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow(COLUMNS)
    for r in rows:
        w.writerow([_csv_value(r.get(c)) for c in COLUMNS])
    return out.getvalue()
