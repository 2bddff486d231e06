"""``velab runs``: every run under some folders, one row each, from the catalogue (velab.catalogue)."""

from __future__ import annotations

import argparse
import sys

from velab.commands.common import DataError, add_json_option, int_range

# the models a fit can name best (velab.fitting.sweep.MAX_M elements; the reduced S1r..S5r), and "none": not fitted
MODEL_NAMES = frozenset(["el", "none"] + [f"s{m}" for m in range(1, 7)] + [f"s{m}r" for m in range(1, 6)])
_SORT_HELP = "start, path, status, title, operator, specimen, rig, q0, beta, rate, duration, best, wave-speed, se, fits, noise"


def _words(text: str) -> tuple[str, ...]:
    return tuple(w.strip() for w in text.split(",") if w.strip())


def register(sub) -> None:
    p = sub.add_parser(
        "runs", help="list and filter every run under folders (the run catalogue)",
        description="One row per run file under the folders (recursively): start time, title / operator / "
                    "specimen, rig, Q0, beta, rate, duration, status and fault flags, the latest fit's best model, "
                    "wave speed +- SE and misfit flag, the number of fits. Damaged files are listed as 'damaged' "
                    "with the reason; a run being recorded as 'recording', one whose recorder died as "
                    "'interrupted'. An index in the user's cache (XDG_CACHE_HOME/velab, or $VELAB_CATALOGUE) keeps later listings fast: only new or changed "
                    "files are read. Run files are never written.")
    p.add_argument("folders", nargs="*", default=["."], metavar="FOLDER",
                   help="folders (searched recursively) or run files; default: the current folder")
    p.add_argument("--status", action="append", default=[], metavar="S[,S]",
                   help="only runs with this status: recording, interrupted (the recorder died), completed, "
                        "completed-with-faults, stopped, aborted, failed, synthetic, imported, damaged "
                        "(repeat or comma-separate for any of them)")
    p.add_argument("--best", action="append", default=[], metavar="MODEL[,MODEL]",
                   help="only runs whose latest fit's best model is this (EL, S1..S6, S3r...; 'none': not fitted)")
    p.add_argument("--rig", default="", metavar="TEXT", help="only runs whose rig name contains TEXT (any case)")
    p.add_argument("--since", metavar="DATE", help="only runs started on or after DATE (YYYY-MM-DD or ISO 8601)")
    p.add_argument("--until", metavar="DATE", help="only runs started on or before DATE (a bare date: that whole day)")
    p.add_argument("--q0", metavar="MIN:MAX",
                   help="only runs whose steady flow (l/s; the measured one where recorded) is in MIN:MAX "
                        "(either side may be empty), VALUE~TOL, or VALUE (within 3 %%)")
    p.add_argument("--text", action="append", default=[], metavar="WORD",
                   help="only runs whose title, operator, specimen or notes contain WORD (any case; repeat: all)")
    p.add_argument("--sort", default="start", metavar="KEY",
                   help=f"sort by KEY (default start: oldest first); --sort=-KEY for descending: {_SORT_HELP}")
    out = p.add_mutually_exclusive_group()
    add_json_option(out)
    out.add_argument("--csv", action="store_true", help="print every column as CSV on stdout")
    p.add_argument("--jobs", type=int_range(1, 64), default=None,
                   help="worker processes reading new or changed files (default: up to 2, one per core)")
    p.add_argument("--index", metavar="FILE", default=None,
                   help="the index file (default: $VELAB_CATALOGUE, else XDG_CACHE_HOME/velab/catalogue.sqlite)")
    p.add_argument("--rebuild", action="store_true", help="read every file again (the index is otherwise kept)")
    p.set_defaults(func=run)


def filters_of(args: argparse.Namespace):
    """The Filters of the options; a bad value is a one-line DataError (exit 2)."""
    from velab.catalogue.query import STATUSES, Filters, parse_range, parse_when

    status = tuple(s for v in args.status for s in _words(v))
    for s in status:
        if s not in STATUSES:
            raise DataError(f"--status {s}: not a status (one of {', '.join(STATUSES)})")
    when = {}
    for opt, end in (("since", False), ("until", True)):
        v = getattr(args, opt)
        try:
            when[opt] = parse_when(v, end=end) if v else None
        except ValueError as exc:
            raise DataError(f"--{opt}: {exc}") from None
    since, until = when["since"], when["until"]
    q0 = None
    if args.q0 is not None:
        try:
            q0 = parse_range(args.q0)
        except ValueError as exc:
            raise DataError(f"--q0: {exc}") from None
    best = tuple(b for v in args.best for b in _words(v))
    for b in best:
        if b.lower() not in MODEL_NAMES:
            raise DataError(f"--best {b}: not a model velab fits (EL, S1..S6, S1r..S5r, or none: not fitted)")
    return Filters(status=status, best=best, rig=args.rig.strip(),
                   since=since, until=until, text=tuple(w for w in args.text if w.strip()), q0=q0)


def _write_json(rows: list[dict], listing) -> None:
    """One strict JSON document; each row as the index stores it (strict JSON already, rows.dumps) rather than
    encoded again: write_json's indented encoder is pure Python, seconds for 10,000 rows."""
    import json

    from velab.catalogue.rows import dumps
    from velab.commands.common import json_ready

    def text(row: dict) -> str:
        t = listing.texts.get(row["path"])
        if t is None:
            try:
                t = dumps(row)
            except ValueError:  # a non-finite number: null, as write_json does
                t = json.dumps(json_ready(row), allow_nan=False)
        return t

    rest = json.dumps({"not_runs": [{"path": r["path"], "reason": listing.full(r)["reason"]} for r in listing.others],
                       "index": {"path": listing.index_path, "files": listing.files, "read": listing.read,
                                 "removed": listing.removed, "seconds": round(listing.seconds, 3)}},
                      indent=1, allow_nan=False)
    out = sys.stdout
    out.write('{\n "runs": [\n' + ",\n".join(map(text, rows)) + "\n ],\n" + rest[2:] + "\n")
    out.flush()


def run(args: argparse.Namespace) -> int:
    import os

    from velab.catalogue.index import Catalogue
    from velab.catalogue.query import SORT_KEYS, sort_rows, table, to_csv
    from velab.commands.common import ProgressLine

    if args.sort.lstrip("-") not in SORT_KEYS:
        raise DataError(f"--sort {args.sort}: not a sort key (one of {_SORT_HELP})")
    filters = filters_of(args)
    for f in args.folders:
        if not os.path.exists(f):
            raise DataError(f"{f}: no such folder or file")
    with ProgressLine.for_args(args) as progress, Catalogue(args.index, args.folders) as cat:
        listing = cat.update(args.folders, jobs=args.jobs, rebuild=args.rebuild, light=True,
                             progress=lambda done, total: progress.update(f"indexing: {done}/{total} files read"))
    rows = sort_rows(filters.apply(listing.rows), args.sort)  # on the light rows: no JSON decoded for these
    if not args.json:  # the JSON document copies the stored texts; the table and CSV need the rows whole
        rows = [listing.full(r) for r in rows]
    damaged = sum(1 for r in listing.rows if r["status"] == "damaged")
    if args.json:
        _write_json(rows, listing)
    elif args.csv:
        sys.stdout.write(to_csv(rows))
    else:
        print(table(rows, [os.path.abspath(f) for f in args.folders]))
    if not args.json and not args.csv or args.verbose:
        extra = f", {len(listing.others)} HDF5 file(s) that are not runs skipped" if listing.others else ""
        print(f"{len(rows)} of {len(listing.rows)} runs shown ({damaged} damaged{extra}); "
              f"{listing.read} file(s) read, {listing.seconds:.2f} s", file=sys.stderr)
    return 0
