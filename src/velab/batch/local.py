"""How many fit processes a local batch runs (``velab fit --jobs N``): the fits themselves run on the fit
service's worker-process backend (velab.fitservice.process)."""

from __future__ import annotations

import os


def processes_for(jobs: int, runs: int) -> int:
    """Processes used for ``--jobs`` over ``runs`` runs: never more than the runs or the cores."""
    return max(1, min(jobs, runs, os.cpu_count() or 1))
