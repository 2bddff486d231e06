"""Synthetic runs: the paper's numerical experiment (physics.md section 8).

The head at the transducer is the frequency-domain model's response to the
sigmoid closure (full band, the reference), on top of the rig's steady head,
plus zero-mean white Gaussian noise. The noise depends only on the seed and the
time grid, so materials A and B get the same noise, as in the paper.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from velab.config import Material, Rig
from velab.model import valve_flow, valve_head

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


def synthesise(rig: Rig, material: Material, s: SynthSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Time (s from trigger), absolute head (m) and valve flow (m^3/s) of a synthetic run."""
    t = synth_time_grid(s)
    n_pre = int(np.count_nonzero(t < 0))
    h = valve_head(t, rig, material)
    head = rig.steady_head_m + h + synth_noise(s, t.size - n_pre, n_pre)
    return t, head, valve_flow(t, rig)
