"""Error types shared by the whole application.

A :class:`VelabError` is a *user* error (bad config, bad CSV, bad run file, bad
CLI argument, an unsafe manoeuvre): the CLI prints its message on one line and
exits non-zero, without a traceback. Everything else is a bug and keeps its
traceback.
"""


class VelabError(Exception):
    """A problem the user can fix; the message names what is wrong and where."""

    exit_code = 2


class ConfigError(VelabError):
    """A configuration file is missing, malformed, or non-physical."""


class DataError(VelabError):
    """An input data file (CSV, HDF5 run) is malformed or not what was expected."""


class SafetyError(VelabError):
    """A manoeuvre or run was refused because the configured limits forbid it."""

    exit_code = 3
