"""Fit results in a run file: moved to :mod:`velab.runfiles.fits` (kept for existing imports)."""

from velab.runfiles.fits import (  # noqa: F401
    default_fit_name,
    read_fit_dict,
    read_fit_group,
    save_fit,
    sweep_from_dict,
    validate_fit_name,
    write_fit_group,
)
