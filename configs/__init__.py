"""The configurations shipped with velab (installed as ``velab.configs``; data only).

``rigs/``, ``materials/``, ``benches/``, ``devices/`` and ``sim/`` hold TOML files found
through :func:`velab.configpath.find_config` (after a lab's own and the user's folders).
"""
