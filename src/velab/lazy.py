"""A package's public names imported from its modules on first use (PEP 562).

velab.fitting and velab.fitservice name their API at the package (``from velab.fitting import fit_run``)
without importing it with the package: the recorder reads the fit path's policy without loading scipy,
and a fit request is made without the fitter or the process machinery.
"""

from __future__ import annotations

import importlib


def lazy_exports(package: str, namespace: dict, exports: dict[str, str]):
    """The module-level ``__getattr__`` and ``__dir__`` of the package named ``package`` (PEP 562).

    ``exports`` maps each public name to the module of the package that defines it (``"entry"`` for
    ``package.entry``); ``namespace`` is the package's ``globals()``. Reading an exported name imports its
    module and keeps the value in ``namespace``, so later reads are plain attribute reads; any other name
    is an AttributeError, as of a module without it. ``__dir__`` lists what is bound and what is exported.
    """

    def __getattr__(name: str):
        if name not in exports:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{exports[name]}"), name)
        namespace[name] = value
        return value

    def __dir__():
        return sorted(set(namespace) | set(exports))

    return __getattr__, __dir__
