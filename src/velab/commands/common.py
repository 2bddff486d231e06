"""Argument helpers shared by the subcommands."""

from __future__ import annotations

import argparse
from pathlib import Path

from velab.errors import VelabError


def positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not v > 0:
        raise argparse.ArgumentTypeError(f"must be positive: {text!r}")
    return v


def non_negative_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if v < 0 or v != v:
        raise argparse.ArgumentTypeError(f"must not be negative: {text!r}")
    return v


def prepare_output(path: str | Path, force: bool) -> Path:
    """Check an output run path before any work: directory exists, no silent overwrite."""
    path = Path(path)
    if path.suffix.lower() not in (".h5", ".hdf5", ".nxs"):
        raise VelabError(f"{path}: output must be an HDF5 file (.h5)")
    if not path.parent.is_dir():
        raise VelabError(f"{path.parent}: output directory does not exist")
    if path.exists() and not force:
        raise VelabError(f"{path}: already exists (use --force to replace it)")
    # with --force the old file stays until the new one is complete (write_run renames over it)
    return path
