"""The valve head on any sample grid from the time-domain model: :func:`moc_head`.

The closure's flow q(t) = Q(t) - Q0 has a small step at the trigger (0.41 % of Q0
for the reference sigmoid) and is continuous after it. A step at an instant between
two samples is what the frequency model represents exactly (a band-limited
fractional delay, as ``velab.model.valve_head``) and the characteristic grid does
not; the continuous rest is the other way round. So:

* linear laws (the steady law "linear" or "none", unsteady "none" or "vardy-brown"):
  the MOC integrates the continuous part q(t) - q(0+) on a grid that starts at the
  trigger; its head is continuous (kinks only) and a cubic (4-point Lagrange)
  interpolation puts it on the samples; the step's response comes from the full-band
  frequency model at the trigger's exact instant. The sum is exact by superposition;
* nonlinear laws ("quadratic", "brunone"): superposition no longer holds, so the MOC
  integrates the whole flow, step included (sharp, on its grid), and the *linear*
  MOC the step alone; their difference (continuous but for the small difference of
  the two fronts) is resampled with a stencil that never straddles a wave front, and
  the frequency model's step response is added. The step then interacts with the
  nonlinear friction as it does in the pipe (up to 4 cm on the imperial rig), and sits
  at its exact instant, band-limited as in ``valve_head``.

With the linear laws ``moc_head`` agrees with ``valve_head`` up to the MOC's own
(second-order) discretisation error, at any trigger offset (docs/model.md).
"""

from __future__ import annotations

from collections import OrderedDict
from threading import Lock

import numpy as np

from velab.config import Rig
from velab.model import ValveHeadModel, flow_perturbation
from velab.moc import kernel
from velab.moc.solver import check_laws, run

DEFAULT_DT_S = 2e-3  # MOC step when none is given: second order, ~1e-4 hJ on the reference rig (docs/model.md)
_STEP_MODELS: OrderedDict = OrderedDict()
_STEP_LOCK = Lock()
_STEP_CACHE_SIZE = 8


def default_dt_s(rig: Rig) -> float:
    """MOC step: 2 ms, finer for a manoeuvre faster than beta = 42/s (at least 12 steps per 1/beta,
    so that the cubic resampling of the closure stays below 1e-4 of the Joukowsky head)."""
    return min(DEFAULT_DT_S, 1.0 / (12.0 * rig.manoeuvre.beta_per_s))


def n_reaches(rig: Rig, dt_s: float) -> int:
    """Reaches of the characteristic grid, from the rig's *nominal* wave speed.

    Keeping N independent of the wave speed being evaluated (dt' = L / (N a) moves
    instead) makes the head a smooth function of a: finite-difference Jacobians see
    no jump where N would change.
    """
    if not dt_s > 0:
        raise ValueError(f"dt_s must be positive, got {dt_s}")
    return max(2, int(round(rig.pipe.length_m / (rig.nominal_wave_speed_m_s * dt_s))))


def _step_model(rig: Rig, t: np.ndarray) -> ValveHeadModel:
    """Full-band frequency model of a unit flow step at the trigger on grid t (cached per rig and grid)."""
    key = (rig, float(t[0]), float(t[1] - t[0]), t.size)
    with _STEP_LOCK:
        model = _STEP_MODELS.get(key)
        if model is not None:
            _STEP_MODELS.move_to_end(key)
            return model
    model = ValveHeadModel(rig, t, band_hz=None, trigger_step=1.0)
    with _STEP_LOCK:
        _STEP_MODELS[key] = model
        while len(_STEP_MODELS) > _STEP_CACHE_SIZE:
            _STEP_MODELS.popitem(last=False)
    return model


def moc_head(rig: Rig, wave_speed_m_s: float, J_rel, tau_s, t_s, *, friction: str | None = None,
             unsteady: str | None = None, dt_s: float | None = None, flow=None) -> np.ndarray:
    """Head perturbation (m) at the valve on the sample grid t_s, from the time-domain model.

    t_s : uniform grid, s from the trigger; it may start negative (zeros before 0) and
        the trigger may fall between samples.
    wave_speed_m_s, J_rel, tau_s : wave speed a and the Kelvin-Voigt elements as
        dimensionless J'_k (J_k a^2 rho alpha D / e, as ``velab.model.creep_scale``) and
        retardation times tau_k: the parameters of ``ValveHeadModel.head_params(a, J_rel, tau)``.
    friction : steady law ``"quadratic"``, ``"linear"``, ``"none"``; None -> ``rig.friction``.
    unsteady : ``"none"``, ``"vardy-brown"``, ``"brunone"``; None -> ``rig.friction_unsteady``.
    dt_s : MOC step (default :func:`default_dt_s`, 1 ms on the reference rig); the grid has
        N = round(L / (a_nominal dt_s)) reaches and its step is L / (N a).
    flow : optional callable t -> q(t), the valve's flow perturbation for t >= 0 (m^3/s;
        default the rig's sigmoid). Its value at t = 0 is the step at the trigger.
    """
    friction = rig.friction if friction is None else friction
    unsteady = rig.friction_unsteady if unsteady is None else unsteady
    check_laws(friction, unsteady)
    t = np.asarray(t_s, dtype=float)
    if t.ndim != 1 or t.size < 2:
        raise ValueError("time grid must be a 1-D array of at least 2 samples")
    a = float(wave_speed_m_s)
    if not a > 0:
        raise ValueError(f"wave speed must be positive, got {wave_speed_m_s}")
    out = np.zeros(t.size)
    after = t >= 0.0
    if not after.any():
        return out
    n_reach = n_reaches(rig, default_dt_s(rig) if dt_s is None else float(dt_s))
    dt = rig.pipe.length_m / (n_reach * a)
    n_steps = int(np.floor(t[-1] / dt)) + 4  # the stencil reaches three points past the last sample
    t_grid = np.arange(n_steps) * dt
    q_of = (lambda x: flow_perturbation(x, rig)) if flow is None else flow
    step = float(np.asarray(q_of(np.zeros(1)), dtype=float).reshape(-1)[0])
    q_grid = np.asarray(q_of(t_grid), dtype=float)
    # the linear laws closest to the requested ones: the step's response is taken with them
    lin_friction = "none" if friction == "none" else "linear"
    lin_unsteady = "vardy-brown" if unsteady == "vardy-brown" else "none"
    # (in laminar flow the "quadratic" law is Poiseuille's, linear)
    linear = (friction == lin_friction or rig.laminar) and unsteady == lin_unsteady
    t_after = np.ascontiguousarray(t[after])
    if linear or step == 0.0:
        head_grid, _ = run(rig, J_rel, tau_s, q_grid - step, n_reach, dt, a, friction, unsteady)
        out[after] = kernel.resample_cubic(head_grid, dt, t_after, 0)
    else:
        head_grid, _ = run(rig, J_rel, tau_s, q_grid, n_reach, dt, a, friction, unsteady)
        step_grid, _ = run(rig, J_rel, tau_s, np.full(n_steps, step), n_reach, dt, a, lin_friction, lin_unsteady)
        out[after] = kernel.resample_cubic(head_grid - step_grid, dt, t_after, 2 * n_reach)
    if step != 0.0:
        lin = rig.with_changes(friction=lin_friction, friction_unsteady=lin_unsteady)
        h_step = _step_model(lin, t).head_params(a, np.asarray(J_rel, dtype=float), np.asarray(tau_s, dtype=float))
        # (the band-limited step's pre-ringing on a sample less than half a step before the
        # trigger, which valve_head keeps, is dropped: zeros before the trigger)
        out[after] += step * h_step[after]
    return out


def warm_up() -> None:
    """Compile (first use on a machine, a few seconds) or load from numba's cache (about 0.1 s)
    the kernels, on a tiny problem: call it before a thread with a deadline needs the model."""
    q = np.linspace(0.0, -1e-3, 8)
    for mode in (kernel.UNSTEADY_NONE, kernel.UNSTEADY_WEIGHTING):
        kernel.march(2, 1.0, q, kernel.STEADY_QUADRATIC, 0.0, 1e-3, 1e-3, np.ones(1), np.ones(1) * 0.5,
                     np.ones(1), np.ones(1) * 0.1, np.ones(1) * 0.01, 0.1, mode, np.ones(1) * 0.5, np.ones(1), 0.0, 0.0)
    kernel.resample_cubic(q, 1.0, np.linspace(0.0, 4.0, 5), 4)
