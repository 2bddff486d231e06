"""The flow at the valve that drives the model: ``ValveInput``, and the flows it is built from.

The frequency-domain model (velab.model) takes q(t) = Q(t) - Q0 as its input. A real valve moves in
*position* and the flow obeys the orifice law through the valve pair (physics.md section 10, velab.valvelaw),

    Q(t) = Q0 tau(t) sqrt((Hv0 + h(t)) / Hv0),

with the head rise h the *measured* one (the record holds it), so the input stays linear for the model:
``position_flow`` from a recorded position, ``closure_flow`` from a fitted closure (velab.fitting.closure),
the coupling's head low-passed and taken over the closure's span (``coupling_head``, ``closure_coupling``: the
measured head, or a calibrated model's head once a wall is fitted); ``result_flow`` rebuilds the flow a stored
fit was driven by.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from velab.filters import butter_lowpass_sos, sosfiltfilt
from velab.rig import Rig
from velab.fitting.friction import TimeDomainModel
from velab.model import ValveHeadModel, flow_perturbation, manoeuvre_band_hz
from velab.valvelaw import commanded_position_pct, orifice_coupling
from velab.fitting.closure import PARAM_NAMES, closure_opening, tail_shape


# the closure is fitted before the first reflection returns to the valve (2L/a), or over 1.5 x its
# commanded span if that is longer: there the head is the pipe's characteristic impedance times the
# flow, and the wall acts only through its fastest creep (one Kelvin-Voigt element stands in for it)
CLOSURE_SPAN_FACTOR = 1.5


COUPLING_SPAN_FACTOR = 3.0  # the coupling's head is filtered over this multiple of the closure's window


COUPLING_BAND_FACTOR = 2.0  # the coupling's head is low-passed at this multiple of the manoeuvre's band


@dataclass(frozen=True)
class ValveInput:
    """The flow at the valve that drives the model, on the fit's grid, and how it was obtained."""

    source: str  # "position" | "fitted" | "rig" (the rig's sigmoid: no record of the head to couple)
    flow: np.ndarray  # q(t) = Q(t) - Q0 on the record's grid (0 before the trigger), m^3/s
    params: dict = field(default_factory=dict)  # the fitted closure's parameters
    se: dict = field(default_factory=dict)  # and their standard errors
    text: str = ""
    k: int = 0  # nuisance parameters fitted (added to every model's count)
    gain: float = math.nan  # n ln(F before / F after) of its refinement on the whole window (refine_closure)
    # other closures of the first part (the first part does not tell them apart): the whole-window refinement
    # also starts from them
    alternatives: tuple = ()
    refined_with: str = ""  # the model whose wall the closure was refined with (velab.fitting.refine), if it was
    # the calibrated model whose head the orifice coupling takes (``closure_coupling``): {"wave_speed_m_s", "J_rel",
    # "tau_s", "closure": {PARAM_NAMES: value}}; {} for the measured head
    coupling: dict = field(default_factory=dict)
    # "fitted": the closure's shape (power, loss share, tail) fitted; "rig": held at the valve the rig file
    # describes (``rig_shape``), only its timing fitted (``choose_closure``)
    shape: str = "fitted"
    early_F: float = math.nan  # the closure fit's mean squared residual on the record's first part, and its samples
    early_n: int = 0
    shape_gain: float = math.nan  # n ln F the free shape gained over the rig's on the first part (choose_closure)

    def describe(self) -> dict:
        out = {"source": self.source, "params": dict(self.params), "se": dict(self.se), "text": self.text,
               "nuisance_parameters": self.k}
        if self.source == "fitted":
            out["shape"] = self.shape
            if math.isfinite(self.shape_gain):
                out["shape_gain"] = self.shape_gain
        if self.refined_with:
            out["refined_with"] = self.refined_with
        if self.coupling:
            out["coupling_head"] = {k: (dict(v) if isinstance(v, dict) else v) for k, v in self.coupling.items()}
        return out


def coupling_head(t, h, rig: Rig) -> np.ndarray:
    """The measured head rise as the orifice coupling takes it: low-passed (zero phase) at twice the
    manoeuvre's band, so that the transducer's noise does not enter the flow (the head rise of a
    closure is slower than that)."""
    t = np.asarray(t, dtype=float)
    h = np.asarray(h, dtype=float)
    if t.size < 32:
        return h
    fs = 1.0 / float(t[1] - t[0])
    fc = COUPLING_BAND_FACTOR * manoeuvre_band_hz(rig)
    if fc >= 0.45 * fs:
        return h
    return sosfiltfilt(butter_lowpass_sos(4, fc, fs), h)


def closure_flow(t, h, rig: Rig, params) -> np.ndarray:
    """q(t) of the parametric closure (``PARAM_NAMES`` order) with the head rise h (``coupling_head``)."""
    beta, t_half, power, share, kappa, tail = params
    c = orifice_coupling(h, rig.valve_head_m)
    with np.errstate(divide="ignore"):
        ck = np.where(c > 0, c ** kappa, 0.0 if kappa > 0 else 1.0)
    q = rig.steady_flow_m3_s * (closure_opening(t, beta, t_half, power, share, tail, tail_shape(rig)) * ck - 1.0)
    return np.where(np.asarray(t) >= 0, q, 0.0)


def position_flow(t, h, position_pct, rig: Rig) -> np.ndarray:
    """q(t) from the recorded valve position through the rig's valve (law, characteristic, share)."""
    t = np.asarray(t, dtype=float)
    p = np.clip(np.asarray(position_pct, dtype=float), 0.0, 100.0)
    q0 = rig.steady_flow_m3_s
    if rig.valve.law == "imposed":
        q = q0 * (p / 100.0 - 1.0)
    else:
        q = q0 * (rig.valve.opening(p) * orifice_coupling(h, rig.valve_head_m) - 1.0)
    return np.where(t >= 0, q, 0.0)


def closing_position(t, position_pct, rig: Rig) -> np.ndarray:
    """The recorded position as the valve's stroke: low-passed like the coupling's head, then its
    running minimum after the trigger (a closure only closes). Near shut a steep characteristic turns
    the feedback's noise into flow (a quick-opening valve passes 6 % of Q0 at 0.02 % open with a 5 %
    loss share); the running minimum reaches the shut valve and stays there."""
    t = np.asarray(t, dtype=float)
    p = coupling_head(t, np.asarray(position_pct, dtype=float), rig)
    after = t >= 0
    p[after] = np.minimum.accumulate(p[after])
    return np.clip(p, 0.0, 100.0)


def from_position(t, h, position_pct, rig: Rig) -> ValveInput:
    position_pct = closing_position(t, position_pct, rig)
    v = rig.valve
    text = ("flow at the valve from the recorded valve position: "
            + ("Q0 p/100 (the rig's imposed-flow valve)" if v.law == "imposed" else
               f"{v.describe()}, orifice coupling from the measured head"))
    return ValveInput("position", position_flow(t, h, position_pct, rig), text=text)


def early_window_s(rig: Rig, window_s: float) -> float:
    """Up to the first reflection's return, 2L/a, or 1.5 x the commanded closure (down to 0.1 %)."""
    closure = rig.manoeuvre.closed_s
    return min(window_s, max(2.0 * rig.pipe.length_m / rig.nominal_wave_speed_m_s, CLOSURE_SPAN_FACTOR * closure))


def tm_flow(t, q):
    """The flow on the grid as the time-domain model takes it (t -> q, linear between samples)."""
    return lambda s: np.interp(s, t, q)


def coupling_model(a: float, J_rel, tau, closure) -> dict:
    """``ValveInput.coupling``: the model (wall, closure's parameters in PARAM_NAMES order) whose head the orifice
    coupling takes (``closure_coupling``)."""
    return {"wave_speed_m_s": float(a), "J_rel": [float(v) for v in J_rel], "tau_s": [float(v) for v in tau],
            "closure": dict(zip(PARAM_NAMES, (float(v) for v in closure)))}


def closure_coupling(t, d, rig: Rig, model: dict | None, measured=None) -> np.ndarray:
    """The head rise a fitted closure's orifice coupling takes, on t (from the trigger): the head of ``model``
    (``ValveInput.coupling``: a calibrated wall and the closure, the time-domain model with a nonlinear
    friction, its flow built on the measured coupling head) over the coupling's span, where the valve closes;
    the measured head low-passed (``_coupling``; ``measured`` if already computed) without a model and after
    the span (the valve shut, the coupling idle).

    The measured head carries the record's noise into the flow (a model error of 4.5 mm rms on material A at
    sigma 0.1 m, 16 in n ln F per 8 s run, correlated with the noise): the fit's parameters took it up (the
    fitted coupling exponent was pulled toward 0 and the fast element with it; held at the rig's 1, a
    quick-opening valve's wave speed came out 0.36-0.39 m/s high for standard errors of 0.07). The head of
    the calibrated model has no noise (velab.fitting.refine sets it)."""
    t = np.asarray(t, dtype=float)
    hc = _coupling(t, np.asarray(d, dtype=float), rig) if measured is None else np.array(measured, dtype=float)
    if not model:
        return hc
    ne = min(t.size, max(16, int(np.searchsorted(t, COUPLING_SPAN_FACTOR * early_window_s(rig, math.inf)))))
    te = t[:ne]
    q = closure_flow(te, hc[:ne], rig, [float(model["closure"].get(k, 0.0)) for k in PARAM_NAMES])
    a, J, tau = model["wave_speed_m_s"], np.asarray(model["J_rel"], dtype=float), np.asarray(model["tau_s"], dtype=float)
    tm = TimeDomainModel(rig, te)
    if tm.active:
        hc[:ne] = tm.head(a, J, tau, flow=tm_flow(te, q))
    else:
        vm = ValveHeadModel(rig, te, band_hz=None, flow=q)
        hc[:ne] = vm.head_of(vm.impedance(a, J, tau), vm.flow_sums(q))
    return hc


def _coupling(t: np.ndarray, d: np.ndarray, rig: Rig) -> np.ndarray:
    """The head rise the orifice coupling takes: ``coupling_head`` over a span that does not depend on
    the window's length (a first part and the whole window of one record see the same closure); after it
    the valve is shut and the coupling idle."""
    span = int(np.searchsorted(t, COUPLING_SPAN_FACTOR * early_window_s(rig, math.inf)))
    hc = np.asarray(d, dtype=float).copy()
    hc[:span] = coupling_head(t[:span], hc[:span], rig)
    return hc


def result_flow(settings: dict, t, h, rig: Rig, position_pct=None) -> np.ndarray | None:
    """The flow at the valve a stored fit was driven by (its ``settings["manoeuvre"]``), rebuilt on the
    grid t (s from the trigger) from the head perturbation h there and the recorded position: what a
    figure needs to draw the fitted models. None for fits made before the manoeuvre was an input (the
    rig's sigmoid)."""
    man = (settings or {}).get("manoeuvre")
    if not man:
        return None
    t = np.asarray(t, dtype=float)
    source = man.get("source")
    if source == "rig":
        return flow_perturbation(t, rig)
    hc = _coupling(t, np.asarray(h, dtype=float), rig)
    if source == "position":
        if position_pct is None:  # (a figure without the position record: the commanded one stands in)
            m = rig.manoeuvre
            position_pct = commanded_position_pct(t, m.beta_per_s, m.gamma)
        return position_flow(t, hc, closing_position(t, position_pct, rig), rig)
    if source == "fitted":
        hc = closure_coupling(t, h, rig, man.get("coupling_head"), measured=hc)
        return closure_flow(t, hc, rig, [float(man["params"].get(k, 0.0)) for k in PARAM_NAMES])
    return None
