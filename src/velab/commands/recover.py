"""``velab recover``: a closed copy of a run whose recorder was killed."""

from __future__ import annotations

import argparse

from velab.commands.common import add_json_option, write_json


def register(sub) -> None:
    p = sub.add_parser(
        "recover",
        help="copy a run left open by a killed recorder into a closed file",
        description="A recording killed mid-run (SIGKILL, power loss) leaves a valid file with every flushed "
        "sample, but HDF5 keeps it flagged as open for writing, so fits cannot be saved into it. This writes "
        "a closed copy (default NAME.recovered.h5) and leaves the original untouched.",
    )
    p.add_argument("run", help="the run file")
    p.add_argument("-o", "--output", help="the copy (default: NAME.recovered.h5 beside the run)")
    add_json_option(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from velab.runfile import recover_run

    dst, n = recover_run(args.run, args.output)
    if args.json:
        write_json({"source": str(args.run), "path": str(dst), "n_samples": int(n)})
        return 0
    print(f"wrote {dst}: {n} samples; fit it with `velab fit {dst}`")
    return 0
