"""The manoeuvre in the fit: which flow at the valve drives the model (``valve_input``).

``"position"``: the record holds the valve position and the rig describes the valve: the opening from the
recorded position (velab.fitting.flows). ``"fitted"``: no position record: the closure fitted as nuisance
parameters (velab.fitting.closurefit). ``"rig"``: the rig's commanded sigmoid imposed as the flow (the
paper's model). A closure fitted once (``closure``: a refined one) drives the window as it is.
"""

from __future__ import annotations

import math

import numpy as np

from velab.fitting.options import MANOEUVRES
from velab.rig import Rig
from velab.errors import DataError
from velab.fitting.friction import TimeDomainModel
from velab.model import flow_perturbation
from velab.fitting.closure import FITTED, PARAM_NAMES
from velab.fitting.closurefit import choose_closure, fit_closure
from velab.fitting.flows import ValveInput, _coupling, closure_coupling, closure_flow, from_position


# a head-only record's closure (every fit path: single, sections, joint): the shape of the valve its rig file
# describes unless the record's first part shows another (choose_closure)
CLOSURE_SHAPE = "auto"


MODES = MANOEUVRES  # (velab.fitting.options: the choice's values)


def valve_input(t, d, rig: Rig, window_s: float, *, position_pct=None, mode: str = "auto",
                closure: ValveInput | dict | None = None, shape: str = "fitted") -> ValveInput:
    """The flow at the valve for a prepared record (t from the trigger, d the head perturbation):
    ``mode`` "auto" -- from the recorded position if there is one, else the fitted closure;
    "fitted" -- the fitted closure even with a position record; "rig" -- the rig's commanded sigmoid
    imposed as the flow (the paper's model: no coupling, nothing fitted). ``closure``: a closure
    already fitted on this record's first part (a refinement's, velab.fitting.parts.Record.refine): its
    parameters drive this window too, and the closure is not fitted again. ``shape``: "fitted" (the closure's
    shape fitted), "auto" (``choose_closure``: the rig's valve's shape unless the record shows another)."""
    if mode not in MODES:
        raise DataError(f"unknown manoeuvre input {mode!r} (choose from {', '.join(MODES)})")
    t = np.asarray(t, dtype=float)
    if mode == "rig":
        return ValveInput("rig", flow_perturbation(t, rig),
                          text="flow at the valve imposed as the rig's sigmoid Q0 / (1 + exp(beta t + gamma)) "
                               "(the paper's model: no valve law)")
    hc = _coupling(t, d, rig)
    if position_pct is not None and mode == "auto":
        return from_position(t, hc, position_pct, rig)
    old = closure.describe() if isinstance(closure, ValveInput) else closure
    if old and old.get("source") == "fitted":
        params = {k: float(old["params"].get(k, 0.0)) for k in PARAM_NAMES}
        coupling = dict(old.get("coupling_head") or {})
        hc = closure_coupling(t, d, rig, coupling, measured=hc)
        return ValveInput("fitted", closure_flow(t, hc, rig, [params[k] for k in PARAM_NAMES]), params,
                          dict(old.get("se", {})), old.get("text", ""), k=old.get("nuisance_parameters", FITTED),
                          refined_with=old.get("refined_with", ""), coupling=coupling,
                          shape=old.get("shape", "fitted"), shape_gain=float(old.get("shape_gain", math.nan)))
    if shape == "auto":
        return choose_closure(t, d, rig, window_s, TimeDomainModel(rig, t), coupling=hc)
    return fit_closure(t, d, rig, window_s, TimeDomainModel(rig, t), coupling=hc)
