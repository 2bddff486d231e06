"""``velab info``: a readable summary of a run file and its fits (``--json``: one strict JSON document)."""

from __future__ import annotations

import argparse
import sys

from velab.commands.common import add_json_option, write_json
from velab.errors import VelabError


def register(sub) -> None:
    p = sub.add_parser("info", help="summarise a run file and its fits",
                       description="Print what a run file holds: status, timing, rig, manoeuvre, material, events, "
                       "gaps, fits. A damaged file is reported on one line (exit 2).")
    p.add_argument("runs", nargs="+", help="run files (.h5)")
    add_json_option(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from velab.runfiles import read_run
    from velab.runfiles.summary import as_dict, describe

    if args.json:
        docs, failed = [], 0
        for path in args.runs:
            try:
                docs.append(as_dict(read_run(path)))
            except VelabError as exc:
                docs.append({"path": str(path), "error": str(exc)})
                print(f"velab: {exc}", file=sys.stderr)
                failed += 1
        write_json(docs[0] if len(docs) == 1 else {"runs": docs})
        return 2 if failed else 0
    for i, path in enumerate(args.runs):
        if i:
            print()
        print(describe(read_run(path)))
    return 0
