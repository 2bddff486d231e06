"""Helpers shared by the subcommands: argument domains, output paths, strict JSON, progress.

Light on purpose (standard library only): every command module imports it while
``velab --help`` builds the parser.

Argument types (use them for every numeric option; each carries its domain so the
CLI fuzz test can aim just outside it)::

    p.add_argument("--rate", type=float_range(1.0, 1e6, units="Hz"))
    p.add_argument("--noise", type=non_negative_float)
    p.add_argument("--jobs", type=int_range(1, 64))
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import shutil
import sys
import time
from pathlib import Path

from velab.errors import DataError, VelabError, one_line  # noqa: F401  (one_line: for the commands)

log = logging.getLogger("velab")


# ----------------------------------------------------------------- argument domains


class Number:
    """An argparse ``type``: a finite int or float within [lo, hi] (either end may be open or absent).

    ``Number(float, 0, None, lo_open=True)`` is a positive finite float. Out-of-domain
    values are refused by argparse as ``argument --rate: must be ... (got '1e9')``, exit 2.
    """

    def __init__(self, kind: type = float, lo: float | None = None, hi: float | None = None, *,
                 lo_open: bool = False, hi_open: bool = False, units: str = ""):
        if kind not in (int, float):
            raise TypeError("kind must be int or float")
        self.kind, self.lo, self.hi, self.lo_open, self.hi_open, self.units = kind, lo, hi, lo_open, hi_open, units
        self.__name__ = self.describe()  # argparse names the type in some messages

    def describe(self) -> str:
        what = "an integer" if self.kind is int else "a finite number"
        u = f" {self.units}" if self.units else ""
        if self.lo is not None and self.hi is not None:
            left = "(" if self.lo_open else "["
            right = ")" if self.hi_open else "]"
            return f"{what} in {left}{self.lo:g}, {self.hi:g}{right}{u}"
        if self.lo is not None:
            if self.lo == 0:
                return f"{what} > 0" if self.lo_open else f"{what} >= 0"
            return f"{what} {'>' if self.lo_open else '>='} {self.lo:g}{u}"
        if self.hi is not None:
            return f"{what} {'<' if self.hi_open else '<='} {self.hi:g}{u}"
        return what

    def contains(self, v: float) -> bool:
        if not math.isfinite(v):
            return False
        if self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo):
            return False
        if self.hi is not None and (v >= self.hi if self.hi_open else v > self.hi):
            return False
        return True

    def __call__(self, text: str):
        s = str(text).strip()
        try:
            v = int(s, 10) if self.kind is int else float(s)
        except (ValueError, OverflowError):
            raise argparse.ArgumentTypeError(f"must be {self.describe()} (got {text!r})") from None
        try:
            ok = self.contains(float(v))
        except OverflowError:  # an integer beyond any float
            ok = False
        if not ok:
            raise argparse.ArgumentTypeError(f"must be {self.describe()} (got {text!r})")
        return v

    def __repr__(self) -> str:
        return f"Number({self.describe()})"


def float_range(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
                hi_open: bool = False, units: str = "") -> Number:
    """A finite float in [lo, hi] (``lo_open``/``hi_open`` make an end exclusive; None: unbounded)."""
    return Number(float, lo, hi, lo_open=lo_open, hi_open=hi_open, units=units)


def int_range(lo: int | None = None, hi: int | None = None) -> Number:
    """An integer in [lo, hi] (None: unbounded)."""
    return Number(int, lo, hi)


def bound_float(bound) -> Number:
    """A finite float inside a :class:`velab.bounds.Bound` (the same bound the config and run-file doors use)."""
    return Number(float, bound.lo, bound.hi, lo_open=bound.lo_open, units=bound.units)


finite_float = Number(float)
positive_float = Number(float, 0, None, lo_open=True)
non_negative_float = Number(float, 0, None)
positive_int = Number(int, 1, None)


# ----------------------------------------------------------------- files


def check_input_file(path: str | Path, what: str = "file", max_bytes: int | None = None) -> Path:
    """An existing regular file below ``max_bytes``; else a one-line DataError naming it."""
    from velab.inputfiles import check_input_file as check

    check(path, what, max_bytes)
    return Path(path)


def check_output_path(path: str | Path, suffixes: tuple[str, ...] | None = None, what: str = "output") -> Path:
    """An output file we can create: its directory exists and is a directory, its suffix is known."""
    path = Path(path)
    if suffixes and path.suffix.lower() not in suffixes:
        raise DataError(f"{path}: {what} must be a {' or '.join(suffixes)} file")
    parent = path.parent
    if not parent.is_dir():
        raise DataError(f"{parent}: {what} directory does not exist")
    if path.is_dir():
        raise DataError(f"{path}: is a directory, expected a {what} file name")
    return path


def prepare_output(path: str | Path, force: bool) -> Path:
    """Check an output run path before any work: directory exists, no silent overwrite."""
    path = check_output_path(path, (".h5", ".hdf5", ".nxs"), "output run")
    if path.exists() and not force:
        raise VelabError(f"{path}: already exists (use --force to replace it)")
    # with --force the old file stays until the new one is complete (write_run renames over it)
    return path


# ----------------------------------------------------------------- JSON


def json_ready(o):
    """A JSON-safe copy: NaN/inf -> None, numpy scalars/arrays -> Python, tuples -> lists, paths -> str."""
    if isinstance(o, float):
        return o if math.isfinite(o) else None
    if isinstance(o, (str, int, bool)) or o is None:
        return o
    if isinstance(o, dict):
        return {str(k): json_ready(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [json_ready(v) for v in o]
    if isinstance(o, os.PathLike):
        return os.fspath(o)
    if hasattr(o, "dtype") and hasattr(o, "tolist"):  # numpy, without importing it
        return json_ready(o.tolist())
    return str(o)  # dates, enums and the like: their text


def write_json(doc, stream=None) -> None:
    """Print one strict JSON document (RFC 8259: no NaN/Infinity; non-finite numbers are null)."""
    text = json.dumps(json_ready(doc), indent=1, allow_nan=False)
    out = stream if stream is not None else sys.stdout
    out.write(text + "\n")
    out.flush()


# ----------------------------------------------------------------- progress


def add_json_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true",
                   help="print one JSON document on stdout (strict JSON: non-finite numbers are null)")


class ProgressLine:
    """Progress on stderr, never stdout. On a terminal: one line redrawn in place. Not on a
    terminal: nothing, unless -v, then plain log lines (logger ``velab``, level INFO).
    ``--quiet`` silences it everywhere."""

    def __init__(self, mode: str, stream=None, interval_s: float = 0.1):
        self.mode = mode  # "tty" | "log" | "off"
        self.stream = stream or sys.stderr
        self.interval_s = interval_s
        self._last = 0.0
        self._shown = False

    @classmethod
    def for_args(cls, args, stream=None) -> "ProgressLine":
        stream = stream or sys.stderr
        if getattr(args, "quiet", False):
            return cls("off", stream)
        try:
            tty = stream.isatty()
        except (AttributeError, ValueError):
            tty = False
        if tty:
            return cls("tty", stream)
        return cls("log" if getattr(args, "verbose", 0) else "off", stream)

    def update(self, text: str, force: bool = False) -> None:
        if self.mode == "log":
            log.info("%s", text)
        elif self.mode == "tty":
            now = time.monotonic()
            if not force and now - self._last < self.interval_s:
                return
            self._last = now
            width = max(10, shutil.get_terminal_size((80, 24)).columns - 1)
            self.stream.write("\r\x1b[2K" + text[:width])
            self.stream.flush()
            self._shown = True

    def close(self) -> None:
        if self._shown:
            self.stream.write("\r\x1b[2K")
            self.stream.flush()
            self._shown = False

    def __enter__(self) -> "ProgressLine":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
