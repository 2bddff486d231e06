"""Deprecated: fit results in a run file are :mod:`velab.runfiles.fits`.

Left only while velab.commands.fit and velab.gui.archive_io still import it; delete it with them
(it is the last edge of the fitting -> runfiles -> fitting cycle).
"""

from velab.runfiles.fits import (  # noqa: F401
    default_fit_name,
    read_fit_dict,
    read_fit_group,
    save_fit,
    sweep_from_dict,
    validate_fit_name,
    write_fit_group,
)
