"""The ``velab`` command line.

Each subcommand lives in its own module under :mod:`velab.commands`, listed once in
:data:`COMMAND_MODULES`; the module exposes ``register(subparsers)`` adding an
argparse parser whose ``func(args) -> int`` does the work. A command module's top
level imports only argparse and light helpers (numpy, scipy, h5py, Qt are imported
inside ``func``), so ``velab --help`` starts fast (benchmarks/cli_startup.py).

Global options (before or after the subcommand): ``--version``, ``-v/--verbose``,
``-q/--quiet``, ``--log-file``; logging goes through the ``velab`` logger, set up
once here (:func:`configure_logging`). User errors (:class:`velab.errors.VelabError`)
are printed as one line, ``velab: <message>``, and exit with the codes of
:class:`velab.errors.ExitCode` (docs/cli.md); no traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import signal
import sys
import threading

from velab import __version__
from velab.errors import ExitCode, VelabError, one_line

# Modules that register subcommands, in the order --help lists them: the one registry.
COMMAND_MODULES = (
    "velab.commands.synth",
    "velab.commands.import_csv",
    "velab.commands.info",
    "velab.commands.runs",
    "velab.commands.recover",
    "velab.commands.fit",
    "velab.commands.sim",
    "velab.commands.record",
    "velab.commands.valve",
    "velab.commands.gui",
)

LOGGER = "velab"
_HANDLER_TAG = "_velab_cli_handler"


class _Parser(argparse.ArgumentParser):
    """Bad arguments: one line naming the command and the problem, exit 2 (no usage dump)."""

    def error(self, message: str):  # noqa: D401 - argparse API
        self.exit(ExitCode.BAD_INPUT, f"{self.prog}: {one_line(message)} (see {self.prog} --help)\n")



def _add_global_options(p: argparse.ArgumentParser, top: bool) -> None:
    # Under a subcommand the defaults are SUPPRESSed so that `velab -v fit` is not undone
    # by the subparser's own default (argparse copies a subparser's defaults over the parent's).
    d = (lambda v: v) if top else (lambda v: argparse.SUPPRESS)
    g = p.add_argument_group("global options")
    g.add_argument("-v", "--verbose", action="count", default=d(0),
                   help="more diagnostics on stderr (-v: progress and info, -vv: debug)")
    g.add_argument("-q", "--quiet", action="store_true", default=d(False),
                   help="errors only on stderr (no progress, no warnings)")
    g.add_argument("--log-file", metavar="FILE", default=d(None),
                   help="also write the full log (debug level, timestamped) to FILE (appended)")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="velab",
        description="Water-hammer tests on viscoelastic pipes: record, store, calibrate (Sm models by AIC). "
                    "Exit codes: 0 ok, 2 bad input, 3 refused by safety, 4 aborted, 5 device/storage failure, "
                    "130 interrupted (docs/cli.md).",
    )
    parser.add_argument("--version", action="version", version=f"velab {__version__}")
    _add_global_options(parser, top=True)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name == name:  # a command not built yet (another branch adds it)
                continue
            raise
        module.register(sub)
    for p in sub.choices.values():
        _add_global_options(p, top=False)
    return parser


def configure_logging(verbose: int = 0, quiet: bool = False, log_file: str | None = None) -> logging.Logger:
    """Set up the ``velab`` logger once per invocation (idempotent: replaces its own handlers).

    stderr gets warnings (``velab: warning: ...``), with -v info, with -vv debug, with
    --quiet errors only. ``log_file`` gets everything at debug level with timestamps.
    """
    logger = logging.getLogger(LOGGER)
    for h in list(logger.handlers):
        if getattr(h, _HANDLER_TAG, False):
            logger.removeHandler(h)
            h.close()
    level = logging.ERROR if quiet else {0: logging.WARNING, 1: logging.INFO}.get(verbose, logging.DEBUG)
    console = logging.StreamHandler(sys.stderr)
    console.setLevel(level)
    console.setFormatter(_ConsoleFormatter())
    setattr(console, _HANDLER_TAG, True)
    logger.addHandler(console)
    lowest = level
    if log_file:
        try:
            fh = logging.FileHandler(log_file, mode="a", encoding="utf-8")
        except OSError as exc:
            raise VelabError(f"--log-file {log_file}: cannot open: {exc.strerror or exc}") from None
        fh.setLevel(logging.DEBUG)
        fh.setFormatter(logging.Formatter("%(asctime)s %(name)s %(levelname)s %(message)s"))
        setattr(fh, _HANDLER_TAG, True)
        logger.addHandler(fh)
        lowest = logging.DEBUG
    logger.setLevel(lowest)
    return logger


class _ConsoleFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        msg = record.getMessage()
        if record.levelno >= logging.ERROR:
            return f"velab: {msg}"
        if record.levelno >= logging.WARNING:
            return f"velab: warning: {msg}"
        return msg


def _close_logging() -> None:
    """Remove this invocation's handlers (main() may run many times in one process: tests, the GUI)."""
    logger = logging.getLogger(LOGGER)
    for h in list(logger.handlers):
        if getattr(h, _HANDLER_TAG, False):
            logger.removeHandler(h)
            h.close()
    logger.setLevel(logging.NOTSET)


class Terminated(KeyboardInterrupt):
    """SIGTERM, delivered as an interrupt: the command unwinds (partial files removed) and exits 130."""


@contextlib.contextmanager
def _sigterm_interrupts():
    """While a command runs, SIGTERM interrupts it as Ctrl-C does (exit 130, every ``finally`` run: no partial
    file) instead of killing the process (exit 143, a ``.part`` left behind). Only where SIGTERM has its default
    action and on the main thread: a command with its own handler (record, sim) installs it over this one."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGTERM) != signal.SIG_DFL:
        yield
        return

    def on_term(signum, frame):
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a second SIGTERM must not cut the clean-up short
        raise Terminated()

    signal.signal(signal.SIGTERM, on_term)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return ExitCode.BAD_INPUT
    with _sigterm_interrupts():
        return _run(args, argv)


def _run(args, argv) -> int:
    log = logging.getLogger(LOGGER)
    try:
        configure_logging(args.verbose, args.quiet, args.log_file)
        log.debug("velab %s: %s", __version__, " ".join(sys.argv[1:] if argv is None else argv))
        return int(args.func(args) or 0)
    except VelabError as exc:
        log.debug("user error", exc_info=True)
        print(f"velab: {one_line(exc)}", file=sys.stderr)
        return int(exc.exit_code)
    except KeyboardInterrupt as exc:
        print(f"velab: {'terminated (SIGTERM)' if isinstance(exc, Terminated) else 'interrupted'}", file=sys.stderr)
        return ExitCode.INTERRUPTED
    except BrokenPipeError:  # `velab info ... | head`: the reader left; not an error
        return ExitCode.OK
    except Exception as exc:
        code = _device_layer_error(exc)
        if code is None:
            raise  # a bug: keep the traceback
        print(f"velab: {one_line(exc)}", file=sys.stderr)
        return code
    finally:
        _close_logging()


def _device_layer_error(exc: Exception) -> int | None:
    """The device layer's typed errors are user-facing too: a bad profile is bad input, the rest device failures."""
    from velab.drivers.base import DeviceError, ProfileError

    if isinstance(exc, ProfileError):
        return ExitCode.BAD_INPUT
    if isinstance(exc, DeviceError):
        return ExitCode.FAILURE
    return None


if __name__ == "__main__":
    sys.exit(main())
