"""The measured stroke of a fired valve: the sigmoid recovered from a recorded position."""

from __future__ import annotations

import math

import numpy as np

from velab.recording.stroke import fit_stroke


def _position(t, beta, gamma, end, t0, noise=0.0, seed=0):
    p = end + (100.0 - end) / (1.0 + np.exp(beta * (t - t0) + gamma))
    return p + np.random.default_rng(seed).normal(0.0, noise, t.size)


def test_the_sigmoid_of_a_noisy_recorded_position_is_recovered():
    t = np.arange(0.0, 3.0, 1e-3)
    s = fit_stroke(t, _position(t, 32.0, -5.5, 0.0, 1.0, noise=0.05), t0=1.0)
    assert s is not None and s.samples > 50
    assert abs(s.beta_per_s - 32.0) < 0.5 and abs(s.gamma + 5.5) < 0.1
    assert abs(s.closure_s - math.log(81) / 32.0) < 3e-3
    assert s.rms_pct < 0.2


def test_a_stroke_to_a_partial_end_finds_its_end():
    t = np.arange(0.0, 3.0, 1e-3)
    s = fit_stroke(t, _position(t, 20.0, -3.0, 15.0, 0.5, noise=0.02), t0=0.5)
    assert abs(s.end_position_pct - 15.0) < 0.2 and abs(s.beta_per_s - 20.0) < 0.5


def test_no_stroke_or_a_stroke_sampled_too_slowly_is_none():
    t = np.arange(0.0, 3.0, 1e-3)
    assert fit_stroke(t, np.full(t.size, 100.0), t0=1.0) is None
    slow = np.arange(0.0, 3.0, 0.1)  # 10 Hz: at most one sample inside a 0.14 s stroke
    assert fit_stroke(slow, _position(slow, 32.0, -5.5, 0.0, 1.0), t0=1.0) is None


def test_a_stroke_that_is_not_a_sigmoid_shows_in_its_residual():
    t = np.arange(0.0, 3.0, 1e-3)
    ramp = np.clip(100.0 - (t - 1.0) / 0.3 * 100.0, 0.0, 100.0)  # a linear ramp in 0.3 s
    s = fit_stroke(t, ramp, t0=1.0)
    assert s is not None and s.rms_pct > 1.0
