"""Synthetic runs: a known pipe wall on a rig, with the rig's valve and friction, plus noise.

The head at the transducer is the response to the rig's sigmoid manoeuvre, on top
of the rig's steady head, plus zero-mean white Gaussian noise. Which model makes
the head depends on the valve law and the friction laws (the rig's, or overridden):

* the valve law ``"orifice"`` (``rig.valve``, the reference rigs' default, physics.md
  section 10): the actuator moves the butterfly valve along the sigmoid *in position*
  and the flow obeys the orifice law of the valve pair, Q = Q0 tau(p) sqrt((Hv0 + h)/Hv0).
  Nonlinear whatever the friction: always the time-domain model
  (``velab.moc.moc_transient``), which also gives the flow it let through;
* the valve law ``"imposed"`` (the paper's model): the sigmoid is the flow itself. Then
  linear friction laws -- steady ``"linear"`` (the paper's tangent R) or ``"none"``,
  unsteady ``"none"`` or ``"vardy-brown"`` -- are represented exactly by the full-band
  frequency-domain model (``velab.model.valve_head``): with ``"linear"`` this is the
  paper's synthetic experiment (physics.md section 8), bit for bit what velab
  synthesised before nonlinear friction existed; nonlinear laws -- steady
  ``"quadratic"`` or unsteady ``"brunone"`` -- go through the time-domain model.

The noise depends only on the seed and the time grid, so materials A and B get
the same noise, as in the paper.

A rig with several transducers (``[[transducers]]``): :func:`synthesise_sections` gives the head
at every other section (the same model with ``position_m`` / ``sections_m``), each on its own
steady head and with its own noise (seeded from the run's seed and the section's index).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np

from velab.config import Material
from velab.rig import Rig
from velab.model import ValveHeadModel, creep_scale, flow_perturbation, manoeuvre_band_hz, valve_flow, valve_head
from velab.valvelaw import commanded_position_pct, imposed_flow

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


class SynthRecord(NamedTuple):
    """A synthetic run's channels on its time grid (s from the trigger)."""

    time_s: np.ndarray
    head_m: np.ndarray  # absolute head at the transducer, noise included
    flow_m3_s: np.ndarray  # absolute flow through the valve, as the model computed it
    position_pct: np.ndarray | None  # the valve's position (% open) with the orifice law; None when imposed


def friction_is_linear(rig: Rig) -> bool:
    """True if the rig's friction laws are linear in q, so the frequency-domain model is exact."""
    return rig.friction in ("linear", "none") and rig.friction_unsteady in ("none", "vardy-brown")


def uses_frequency_model(rig: Rig) -> bool:
    """True if the frequency-domain model is exact for the rig: imposed flow and linear friction laws."""
    return rig.valve.law == "imposed" and friction_is_linear(rig)


def head_model(rig: Rig) -> str:
    """The model that makes the rig's transient, for reports."""
    return "frequency-domain model" if uses_frequency_model(rig) else "time-domain model (MOC)"


def with_valve_law(rig: Rig, law: str) -> Rig:
    """The rig with its valve pair's law changed (``"orifice"`` or ``"imposed"``), characteristic kept."""
    return rig if rig.valve.law == law else rig.with_changes(valve=replace(rig.valve, law=law))


def flow_band_hz(rig: Rig) -> float:
    """The frequency above which the valve flow's spectrum is negligible (``velab.model.manoeuvre_band_hz``).

    With the orifice law the flow closes faster than the commanded sigmoid in position (a butterfly
    passes most of its flow until the last third of its stroke): the band is that of the sigmoid with
    the same 90 % -> 10 % time as the opening tau(t) (the head's feedback on the flow left out).
    """
    if rig.valve.law == "imposed":
        return manoeuvre_band_hz(rig)
    m = rig.manoeuvre
    dt = m.closure_time_s / 2000.0
    t = np.arange(0.0, -m.gamma / m.beta_per_s + 20.0 / m.beta_per_s, dt)
    tau = rig.valve.opening(commanded_position_pct(t, m.beta_per_s, m.gamma))
    closure = max(dt, t[np.argmax(tau < 0.1)] - t[np.argmax(tau < 0.9)])
    return manoeuvre_band_hz(rig.with_changes(manoeuvre=replace(m, beta_per_s=math.log(81.0) / closure)))


def transient_head(t_s, rig: Rig, material: Material, flow=None) -> np.ndarray:
    """Head perturbation (m) at the valve for an *imposed* valve flow, with the rig's friction laws,
    on the grid t_s (s from the trigger); ``rig.valve`` is not consulted (:func:`transient` is).

    Full-band frequency model for linear friction laws, time-domain model (MOC) otherwise.
    ``flow``: optional callable t -> q(t) (m^3/s, t >= 0) imposed at the valve instead of the
    rig's sigmoid (partial or interrupted closures); with the frequency model its value at the
    first sample at or after the trigger is the step.
    """
    t = np.asarray(t_s, dtype=float)
    if friction_is_linear(rig):
        if flow is None:
            return valve_head(t, rig, material)
        q = np.where(t >= 0, np.asarray(flow(np.maximum(t, 0.0)), dtype=float), 0.0)
        return ValveHeadModel(rig, t, band_hz=None, flow=q).head(material)
    from velab.moc import moc_head  # numba: imported when needed, not at CLI start-up

    return moc_head(rig, *_moc_params(rig, material), t, flow=flow)


def _moc_params(rig: Rig, material: Material):
    a = material.wave_speed_m_s
    J_rel = np.array([e.J_per_pa for e in material.elements], dtype=float) * creep_scale(rig, a)
    tau = np.array([e.tau_s for e in material.elements], dtype=float)
    return a, J_rel, tau


def transient(t_s, rig: Rig, material: Material, position=None) -> tuple[np.ndarray, np.ndarray]:
    """(head, flow) perturbations at the valve on the grid t_s (s from the trigger; zeros before it)
    for the rig's valve law and friction laws.

    ``position``: optional callable t -> p(t), the valve's position (% open) for t >= 0; default
    the rig's commanded sigmoid (full closure). ``rig.valve.law`` "orifice": the flow obeys the
    orifice law on that position (the MOC); "imposed": the flow Q0 p / 100 is imposed (for the
    commanded full closure exactly the paper's sigmoid Q0 / (1 + exp(beta t + gamma))).
    """
    t = np.asarray(t_s, dtype=float)
    if rig.valve.law == "orifice":
        from velab.moc import moc_transient  # numba: imported when needed

        if position is None:
            m = rig.manoeuvre
            position = lambda x: commanded_position_pct(x, m.beta_per_s, m.gamma)  # noqa: E731
        tr = moc_transient(rig, *_moc_params(rig, material), t, position=position)
        return tr.head_m, tr.flow_m3_s
    if position is None:
        return transient_head(t, rig, material), flow_perturbation(t, rig)
    q0 = rig.steady_flow_m3_s
    flow = lambda x: imposed_flow(position(x), q0) - q0  # noqa: E731
    return (transient_head(t, rig, material, flow=flow),
            np.where(t >= 0, flow(np.maximum(t, 0.0)), 0.0))


def section_transients(t_s, rig: Rig, material: Material) -> np.ndarray:
    """Head perturbations at every section of the rig (``rig.sections``), shape (sections, samples), for the
    rig's valve law (the commanded sigmoid) and friction laws: the model :func:`transient` uses."""
    t = np.asarray(t_s, dtype=float)
    xs = [x.position_m for x in rig.sections]
    if uses_frequency_model(rig):
        return np.array([ValveHeadModel(rig, t, band_hz=None, position_m=x).head(material) for x in xs])
    from velab.moc import moc_head, moc_transient  # numba: imported when needed

    if rig.valve.law == "orifice":
        m = rig.manoeuvre
        position = lambda x: commanded_position_pct(x, m.beta_per_s, m.gamma)  # noqa: E731
        return moc_transient(rig, *_moc_params(rig, material), t, position=position, sections_m=xs).section_heads_m
    return moc_head(rig, *_moc_params(rig, material), t, sections_m=xs)


def transient_at_sections(t_s, rig: Rig, material: Material, position=None) -> tuple[np.ndarray, np.ndarray]:
    """(heads, flow) perturbations on the grid t_s: the heads at every section of the rig (``rig.sections``,
    shape (sections, samples)) and the flow through the valve, for the rig's valve law and friction laws on
    ``position`` (as :func:`transient`; default the commanded full closure): one model run gives them all.
    A section at the valve has :func:`transient`'s head."""
    t = np.asarray(t_s, dtype=float)
    xs = [x.position_m for x in rig.sections]
    if position is None and rig.valve.law == "imposed":
        return section_transients(t, rig, material), flow_perturbation(t, rig)
    m = rig.manoeuvre
    if position is None:
        position = lambda x: commanded_position_pct(x, m.beta_per_s, m.gamma)  # noqa: E731
    if rig.valve.law == "orifice":
        from velab.moc import moc_transient  # numba: imported when needed

        tr = moc_transient(rig, *_moc_params(rig, material), t, position=position, sections_m=xs)
        return tr.section_heads_m, tr.flow_m3_s
    q0 = rig.steady_flow_m3_s
    flow = lambda x: imposed_flow(position(x), q0) - q0  # noqa: E731
    q = np.where(t >= 0, flow(np.maximum(t, 0.0)), 0.0)
    if friction_is_linear(rig):
        heads = np.array([ValveHeadModel(rig, t, band_hz=None, flow=q, position_m=x).head(material) for x in xs])
    else:
        from velab.moc import moc_head  # numba: imported when needed

        heads = moc_head(rig, *_moc_params(rig, material), t, flow=flow, sections_m=xs)
    return heads, q


def synthesise_sections(rig: Rig, material: Material, s: SynthSettings) -> dict[str, np.ndarray]:
    """The absolute heads (noise included) of the rig's transducers other than its ``head`` channel's
    (``rig.head_section``, which :func:`synthesise` gives), by name, on :func:`synth_time_grid`. Each has its
    own steady head (the friction loss up to it) and its own noise: the run's seed and the section's index."""
    t = synth_time_grid(s)
    n_pre = int(np.count_nonzero(t < 0))
    heads = section_transients(t, rig, material)
    out = {}
    for i, (sec, h) in enumerate(zip(rig.sections, heads)):
        if sec == rig.head_section:
            continue
        noise = synth_noise(replace(s, seed=int(np.random.SeedSequence([s.seed, i + 1]).generate_state(1)[0])),
                            t.size - n_pre, n_pre)
        out[sec.name] = rig.steady_head_at_m(sec.position_m) + h + noise
    return out


def synthesise(rig: Rig, material: Material, s: SynthSettings) -> SynthRecord:
    """Time (s from trigger), absolute head (m), valve flow (m^3/s) and, with the orifice law, the
    valve position (% open) of a synthetic run.

    The valve and friction laws are the rig's (``rig.with_changes(friction=...)``,
    :func:`with_valve_law` to choose others; the run file's rig snapshot then records the laws
    that made the data).
    """
    t = synth_time_grid(s)
    n_pre = int(np.count_nonzero(t < 0))
    noise = synth_noise(s, t.size - n_pre, n_pre)
    if rig.valve.law == "imposed":
        # the paper's experiment stays what it was, bit for bit
        head = rig.steady_head_m + transient_head(t, rig, material) + noise
        return SynthRecord(t, head, valve_flow(t, rig), None)
    h, q = transient(t, rig, material)
    m = rig.manoeuvre
    return SynthRecord(t, rig.steady_head_m + h + noise, rig.steady_flow_m3_s + q,
                       commanded_position_pct(t, m.beta_per_s, m.gamma))
