"""``velab import``: an archived CSV record into a run file."""

from __future__ import annotations

import argparse
from pathlib import Path

from velab.commands.common import finite_float, prepare_output
from velab.csvimport import PRESSURE_UNITS
from velab.errors import DataError


def register(sub) -> None:
    p = sub.add_parser(
        "import",
        help="import an archived CSV record (time, pressure) as a run file",
        description="Import a CSV with a header row: time in s, and pressure head in m or gauge pressure in "
        "Pa, kPa or bar (--units; converted with rho g of the rig's fluid). The trigger instant is given by "
        "--trigger (default t = 0); the steady head is the mean before it. CSV files up to 256 MiB. A rig with "
        "several [[transducers]]: one pressure column per transducer, the column named as the transducer or "
        "--head-column NAME=COLUMN; stored as the channels 'head' (the valve's) and 'head_NAME'.",
    )
    p.add_argument("csv", help="CSV file")
    p.add_argument("--rig", required=True, help="rig name or TOML file describing the pipe the record comes from")
    p.add_argument("--units", choices=list(PRESSURE_UNITS), default="m", help="pressure column units (default m of head)")
    p.add_argument("--trigger", type=finite_float, default=0.0, help="trigger instant on the file's time axis, s (default 0)")
    p.add_argument("--time-column", help="name of the time column (default: the first)")
    p.add_argument("--value-column", help="name of the pressure column (default: the second)")
    p.add_argument("--head-column", action="append", metavar="NAME=COLUMN", default=[],
                   help="the pressure column of the rig's transducer NAME (repeat for each; default: the column "
                        "named as the transducer, for a rig with several)")
    p.add_argument("--valve-column", help="name of a valve position column (%% open), if the record has one: the "
                                          "fit then takes the manoeuvre from it (default: none, the manoeuvre is fitted)")
    p.add_argument("--title", help="run title (default: the CSV file name)")
    p.add_argument("-o", "--output", required=True, help="run file to write (.h5)")
    p.add_argument("--force", action="store_true", help="replace an existing output file")
    p.set_defaults(func=run)


def parse_head_columns(items: list[str]) -> dict[str, str]:
    """--head-column NAME=COLUMN options -> {NAME: COLUMN}; DataError (one line) for a malformed or repeated one."""
    out: dict[str, str] = {}
    for item in items:
        name, sep, column = item.partition("=")
        name, column = name.strip(), column.strip()
        if not sep or not name or not column:
            raise DataError(f"--head-column {item!r}: expected NAME=COLUMN (a transducer of the rig and a CSV column)")
        if name in out:
            raise DataError(f"--head-column {name}: given twice")
        out[name] = column
    return out


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from velab.config import load_rig
    from velab.csvimport import read_csv_record
    from velab.runfiles import write_run

    rig = load_rig(args.rig)
    out = prepare_output(args.output, args.force)
    rec = read_csv_record(args.csv, rig, units=args.units, time_column=args.time_column, value_column=args.value_column,
                          valve_column=args.valve_column, head_columns=parse_head_columns(args.head_column))
    t = rec.time_s - args.trigger
    if not (t[0] <= 0 <= t[-1]):
        raise DataError(f"--trigger {args.trigger:g} s is outside the record ({rec.time_s[0]:g} .. {rec.time_s[-1]:g} s)")
    if not np.isfinite(t).all() or not all(np.isfinite(h).all() for h in (rec.head_m, *rec.section_heads.values())):
        raise DataError(f"{args.csv}: values too large to convert into head (not finite after conversion)")
    channels = {} if rec.valve_position_pct is None else {"valve_position": (rec.valve_position_pct, "%")}
    by_name = {x.name: x for x in rig.sections}
    for name, h in rec.section_heads.items():  # the other transducers' heads, as the rig names them
        channels[rig.section_channel(by_name[name])] = (h, "m")
    write_run(
        out, rig, t, rec.head_m, status="imported", title=args.title or Path(args.csv).name,
        sample_rate_hz=rec.sample_rate_hz, overwrite=args.force,
        extra_channels=channels or None,
        source={"kind": "csv", "file": str(Path(args.csv).resolve()), "time_column": rec.time_column,
                "value_column": rec.value_column, "units": rec.units, "trigger_s": args.trigger,
                "valve_column": rec.valve_column, **({"head_columns": rec.section_columns} if rec.section_columns else {})},
    )
    n_pre = int(np.count_nonzero(t < 0))
    sections = "" if not rec.section_columns else "; transducers: " + ", ".join(
        f"{n} <- {c}" for n, c in rec.section_columns.items())
    print(f"wrote {out}: {t.size} samples at {rec.sample_rate_hz:g} Hz, {n_pre} before the trigger{sections}")
    return 0
