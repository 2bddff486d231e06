"""The ``velab`` command line.

Each subcommand lives in its own module, which exposes ``register(subparsers)``
adding an argparse parser whose ``func(args) -> int`` does the work. User errors
(:class:`velab.errors.VelabError`) are printed as one line, ``velab: <message>``,
with a non-zero exit and no traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from velab import __version__
from velab.errors import VelabError

# Modules that register subcommands, in the order --help lists them.
COMMAND_MODULES = (
    "velab.commands.synth",
    "velab.commands.import_csv",
    "velab.commands.info",
    "velab.commands.recover",
    "velab.commands.fit",
    "velab.commands.sim",
    "velab.commands.record",
    "velab.commands.valve",
    "velab.commands.gui",
)


class _Parser(argparse.ArgumentParser):
    """Bad arguments: one line naming the command and the problem, exit 2 (no usage dump)."""

    def error(self, message: str):  # noqa: D401 - argparse API
        self.exit(2, f"{self.prog}: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="velab",
        description="Water-hammer tests on viscoelastic pipes: record, store, calibrate (Sm models by AIC).",
    )
    parser.add_argument("--version", action="version", version=f"velab {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name and name.startswith(exc.name):  # a command not built yet
                continue
            raise
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except VelabError as exc:
        print(f"velab: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("velab: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 0


if __name__ == "__main__":
    sys.exit(main())
