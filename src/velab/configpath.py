"""Where configuration files are found: the one lookup for every kind of config.

A config is given either as a path (anything with a directory separator or a
``.toml`` suffix) or as a short name (``perugia``, ``A``, ``sim``), looked up as
``<dir>/<kind>/<name>.toml`` in, first to last:

1. each directory of ``$VELAB_CONFIG_PATH`` (``os.pathsep``-separated: a lab's own
   config folders, laid out like the built-in one);
2. the user's config directory, ``$XDG_CONFIG_HOME/velab`` (default ``~/.config/velab``);
3. the configs shipped inside the package (``velab.configs``, read through
   ``importlib.resources``, so wheels and editable installs behave the same).

Kinds: ``rigs``, ``materials``, ``benches``, ``devices`` (device profiles), ``sim``.
Leaf module: the device layer uses it too.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from velab.errors import ConfigError
from velab.tomlschema import read_toml

ENV_VAR = "VELAB_CONFIG_PATH"
# the simulated bench the commands (record/gui --simulate, velab sim) start unless told: products a lab buys
# (a DATAQ DI-2108, a valve fired by its digital line, the SITRANS flowmeter); "default" is velab's own devices
DEFAULT_SIM = "dataq"
KINDS = {"rigs": "rig", "materials": "material", "benches": "bench", "devices": "device profile",
         "sim": "sim config"}
_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.+-]{0,127}")


def user_config_dir() -> Path:
    """``$XDG_CONFIG_HOME/velab``, or ``~/.config/velab`` (a relative XDG value is ignored, per the spec)."""
    base = os.environ.get("XDG_CONFIG_HOME", "")
    if not base or not os.path.isabs(base):
        base = os.path.join(os.path.expanduser("~"), ".config")
    return Path(base) / "velab"


def builtin_configs():
    """The configs shipped with velab (a Traversable; a plain directory in any pip install)."""
    from importlib import resources  # not at import time: `velab --help` needs no configs

    try:
        return resources.files("velab.configs")
    except ModuleNotFoundError:  # an editable install made before velab.configs existed
        raise ConfigError("the built-in configs (package velab.configs) are not installed: "
                          "reinstall velab (pip install -e . in a checkout)") from None


def search_dirs() -> list:
    """Config roots in lookup order: $VELAB_CONFIG_PATH entries, the user's dir, the built-in configs."""
    dirs: list = [Path(d).expanduser() for d in os.environ.get(ENV_VAR, "").split(os.pathsep) if d.strip()]
    dirs.append(user_config_dir())
    dirs.append(builtin_configs())
    return dirs


def is_path(name_or_path) -> bool:
    """A path (used as given) rather than a short name (looked up)?"""
    if isinstance(name_or_path, os.PathLike):
        return True
    s = str(name_or_path)
    return s.endswith(".toml") or "/" in s or os.sep in s or (os.altsep is not None and os.altsep in s)


def _is_file(candidate) -> bool:
    try:
        return candidate.is_file()
    except OSError:  # an unreadable lab folder must not hide the built-in configs
        return False


def known_configs(kind: str, dirs=None) -> list[str]:
    """Every short name of ``kind`` found in ``dirs`` (default: along the whole search path)."""
    names: set[str] = set()
    for d in search_dirs() if dirs is None else dirs:
        try:
            folder = d / kind
            if not folder.is_dir():
                continue
            names.update(f.name[:-5] for f in folder.iterdir() if f.name.endswith(".toml") and _is_file(f))
        except OSError:
            continue
    return sorted(names)


def find_config(kind: str, name_or_path, *, error: type[Exception] = ConfigError):
    """The file for ``name_or_path``: an explicit path as given, else the first match along the search path.

    Returns a ``Path`` (or, for a built-in config, an ``importlib.resources`` Traversable,
    which is a ``Path`` in every normal install).
    """
    if kind not in KINDS:
        raise ValueError(f"unknown config kind {kind!r}")
    if is_path(name_or_path):
        return Path(name_or_path)
    name = str(name_or_path)
    if not _NAME.fullmatch(name):
        raise error(f"{name!r}: not a {KINDS[kind]} name (letters, digits, _ . + -) nor a path to a .toml file")
    for d in search_dirs():
        candidate = d / kind / f"{name}.toml"
        if _is_file(candidate):
            return candidate
    dirs = search_dirs()
    own = known_configs(kind, dirs[:-1])
    builtin = known_configs(kind, dirs[-1:])
    where = f"${ENV_VAR}, " if len(dirs) > 2 else ""
    raise error(f"{name}: no such {KINDS[kind]} (not a file; looked in {where}{user_config_dir() / kind} and the "
                f"built-in {kind}" + (f"; yours: {', '.join(own)}" if own else "")
                + f"; built-in: {', '.join(builtin) or 'none'})")


def load_config(kind: str, name_or_path, *, error: type[Exception] = ConfigError):
    """``find_config`` + ``read_toml``: ``(path, doc)``, every failure one ``error`` naming the file."""
    return read_toml(find_config(kind, name_or_path, error=error), error=error)


def config_stem(path) -> str:
    """The short name of a config file (its name without ``.toml``)."""
    name = Path(str(path)).name
    return name[:-5] if name.endswith(".toml") else name
