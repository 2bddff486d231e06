"""Error types and exit codes shared by the whole application.

A :class:`VelabError` is a *user* error (bad config, bad CSV, bad run file, bad
CLI argument, an unsafe manoeuvre): the CLI prints its message on one line and
exits with the error's :class:`ExitCode`, without a traceback. Everything else is
a bug and keeps its traceback.
"""

import enum


class ExitCode(enum.IntEnum):
    """The exit status of every ``velab`` command (docs/cli.md). For a batch the worst one decides."""

    OK = 0  # done (a run: completed)
    BAD_INPUT = 2  # bad arguments, configuration or input file (usage errors too)
    REFUSED = 3  # refused by safety: interlock, readiness checks (nothing moved)
    ABORTED = 4  # a run aborted: pressure ceiling, valve fault, operator abort
    FAILURE = 5  # a device or storage failure (device gone, disk full)
    COMPLETED_WITH_FAULTS = 6  # a run completed, but a device fault or flagged samples marked it
    INTERRUPTED = 130  # stopped by Ctrl-C / SIGTERM (128 + SIGINT)

    @classmethod
    def worst(cls, codes) -> "ExitCode":
        """The code of a batch: a bad input outranks a failure, then an abort, a run with faults, an interrupt,
        a refusal."""
        codes = [cls(c) if c in cls._value2member_map_ else cls.FAILURE for c in codes]
        return max(codes, key=_SEVERITY.__getitem__) if codes else cls.OK


_SEVERITY = {ExitCode.OK: 0, ExitCode.REFUSED: 1, ExitCode.INTERRUPTED: 2, ExitCode.COMPLETED_WITH_FAULTS: 3,
             ExitCode.ABORTED: 4, ExitCode.FAILURE: 5, ExitCode.BAD_INPUT: 6}


def one_line(text) -> str:
    """A message on one line: control characters (a newline in a key or file name) shown escaped."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in str(text))


class VelabError(Exception):
    """A problem the user can fix; the message names what is wrong and where."""

    exit_code = ExitCode.BAD_INPUT


class ConfigError(VelabError):
    """A configuration file is missing, malformed, or non-physical."""


class DataError(VelabError):
    """An input data file (CSV, HDF5 run) is malformed or not what was expected."""


class SafetyError(VelabError):
    """A manoeuvre or run was refused because the configured limits forbid it."""

    exit_code = ExitCode.REFUSED


class UnavailableError(VelabError):
    """A device, port or storage the command needs is unavailable (a port in use, a full disk)."""

    exit_code = ExitCode.FAILURE
