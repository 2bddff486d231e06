"""``velab recover``: a closed copy of a run whose writer was killed."""

from __future__ import annotations

import argparse

from velab.commands.common import add_json_option, write_json


def register(sub) -> None:
    p = sub.add_parser(
        "recover",
        help="copy a run left open by a killed writer into a closed file",
        description="A recording killed mid-run (SIGKILL, power loss), or a fit save killed by an older velab, "
        "leaves a file HDF5 keeps flagged as open for writing: it can be read, but nothing can be saved into "
        "it. This writes a clean copy (default NAME.recovered.h5: the flags cleared as h5clear -s does, the "
        "channels cut to one length, end_time set to the last write) and leaves the original untouched.",
    )
    p.add_argument("run", help="the run file")
    p.add_argument("-o", "--output", help="the copy (default: NAME.recovered.h5 beside the run)")
    add_json_option(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from velab.runfiles import recover_run

    dst, n = recover_run(args.run, args.output)
    if args.json:
        write_json({"source": str(args.run), "path": str(dst), "n_samples": int(n)})
    else:
        print(f"wrote {dst}: {n} samples; fit it with `velab fit {dst}`")
    return 0
