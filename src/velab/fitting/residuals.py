"""The best model's residuals on a recorded window, at the fit rate (figures, the GUI's fit panel)."""

from __future__ import annotations

import numpy as np

from velab.fitting.friction import fitted_head
from velab.fitting.flows import result_flow
from velab.fitting.prepare import decimate_head


def best_residuals(t, h, rig, result, model=None, position_pct=None) -> tuple[np.ndarray, np.ndarray]:
    """(t, residual) of the best model (or ``model``) on a window ``t``, ``h`` (s from the trigger, head
    perturbation, m, at the record's rate), taken to the fit rate as the fit path does (the result's
    ``settings["record"]["decimation"]``), so that they compare with the baseline noise band; the model
    is driven by the fit's own flow at the valve (velab.fitting.manoeuvre.result_flow; ``position_pct``
    the recorded valve position on t, if the fit took it). ``h`` is taken from the baseline's steady head;
    the residual is from the model's own (its ``steady_head_offset_m`` added)."""
    t = np.asarray(t, dtype=float)
    h = np.asarray(h, dtype=float)
    q = int(((result.settings or {}).get("record") or {}).get("decimation") or 1)
    hd = decimate_head(h, q)
    td = t[::q][: hd.size]
    f = model if model is not None else result.best
    pd = None if position_pct is None else np.asarray(position_pct, dtype=float)[::q][: td.size]
    flow = result_flow(result.settings, td, hd[: td.size], rig, pd)
    # (the model's head over the steady head it fitted: the baseline's plus its offset, velab.fitting.offset)
    return td, hd[: td.size] - fitted_head(td, rig, f, flow=flow) - f.steady_head_offset_m
