"""Synthetic runs: a known pipe wall on a rig, with the rig's friction, plus noise.

The head at the transducer is the response to the rig's sigmoid closure, on top
of the rig's steady head, plus zero-mean white Gaussian noise. Which model makes
the head depends on the friction laws (the rig's, or overridden):

* linear laws -- steady friction ``"linear"`` (the paper's tangent R) or ``"none"``,
  unsteady ``"none"`` or ``"vardy-brown"`` -- are represented exactly by the
  full-band frequency-domain model (``velab.model.valve_head``): with ``"linear"``
  this is the paper's synthetic experiment (physics.md section 8), bit for bit
  what velab synthesised before nonlinear friction existed;
* nonlinear laws -- steady ``"quadratic"`` (Darcy-Weisbach, the default of the
  reference rigs) or unsteady ``"brunone"`` -- go through the time-domain model
  (``velab.moc.moc_head``): data that the frequency-domain calibration model did
  not generate.

The noise depends only on the seed and the time grid, so materials A and B get
the same noise, as in the paper.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from velab.config import Material, Rig
from velab.model import ValveHeadModel, creep_scale, valve_flow, valve_head

PAPER_SEED = 2018
PAPER_NOISE_STD_M = 0.1


@dataclass(frozen=True)
class SynthSettings:
    noise_std_m: float = PAPER_NOISE_STD_M
    seed: int = PAPER_SEED
    sample_rate_hz: float = 1000.0
    duration_s: float = 20.0  # after the trigger
    pretrigger_s: float = 1.0


def synth_time_grid(s: SynthSettings) -> np.ndarray:
    dt = 1.0 / s.sample_rate_hz
    n_pre = int(round(s.pretrigger_s * s.sample_rate_hz))
    n_post = int(round(s.duration_s * s.sample_rate_hz))
    return (np.arange(-n_pre, n_post)) * dt


def synth_noise(s: SynthSettings, n_post: int, n_pre: int) -> np.ndarray:
    # Post-trigger noise is drawn first so that it is the same sequence whatever
    # the pre-trigger length.
    rng = np.random.default_rng(s.seed)
    post = rng.standard_normal(n_post)
    pre = rng.standard_normal(n_pre)
    return s.noise_std_m * np.concatenate([pre, post])


def friction_is_linear(rig: Rig) -> bool:
    """True if the rig's friction laws are linear in q, so the frequency-domain model is exact."""
    return rig.friction in ("linear", "none") and rig.friction_unsteady in ("none", "vardy-brown")


def transient_head(t_s, rig: Rig, material: Material, flow=None) -> np.ndarray:
    """Head perturbation (m) at the valve for the rig's friction laws, on the grid t_s (s from the trigger).

    Full-band frequency model for linear friction laws, time-domain model (MOC) otherwise.
    ``flow``: optional callable t -> q(t) (m^3/s, t >= 0) imposed at the valve instead of the
    rig's sigmoid (the simulated rig's partial or interrupted closures); with the frequency
    model its value at the first sample at or after the trigger is the step.
    """
    t = np.asarray(t_s, dtype=float)
    if friction_is_linear(rig):
        if flow is None:
            return valve_head(t, rig, material)
        q = np.where(t >= 0, np.asarray(flow(np.maximum(t, 0.0)), dtype=float), 0.0)
        return ValveHeadModel(rig, t, band_hz=None, flow=q).head(material)
    from velab.moc import moc_head  # numba: imported when needed, not at CLI start-up

    a = material.wave_speed_m_s
    J_rel = np.array([e.J_per_pa for e in material.elements], dtype=float) * creep_scale(rig, a)
    tau = np.array([e.tau_s for e in material.elements], dtype=float)
    return moc_head(rig, a, J_rel, tau, t, flow=flow)


def synthesise(rig: Rig, material: Material, s: SynthSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Time (s from trigger), absolute head (m) and valve flow (m^3/s) of a synthetic run.

    The friction laws are the rig's (``rig.with_changes(friction=...)`` to choose others;
    the run file's rig snapshot then records the laws that made the data).
    """
    t = synth_time_grid(s)
    n_pre = int(np.count_nonzero(t < 0))
    h = transient_head(t, rig, material)
    head = rig.steady_head_m + h + synth_noise(s, t.size - n_pre, n_pre)
    return t, head, valve_flow(t, rig)
