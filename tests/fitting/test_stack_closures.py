"""The stacked engine's closure honesty (issue 51: one engine): a single record fitted as a stack of one part
(velab.fitting.sections.fit_sections with the record's one head) gets the single path's closure rules
(velab.fitting.prepare: CLOSURE_ROUNDS, RIVAL_DAIC) in velab.fitting.joint.refine_closures -- the closure
refined again with the named model's wall when the continuation names another model than the one it was
refined with, and the nearest smaller rival within RIVAL_DAIC compared under the closure refined with its own
wall. benchmarks/one_engine.py compares the two engines on the honesty records (docs/decisions.md).

The records: the MOC with quadratic friction and the rig's sigmoid imposed as the flow, sigma 0.1 m, 1 s
pretrigger, 20 s at 1 kHz, fitted head-only with the reference rig file (orifice valve: the closure's shape
and law are fitted), as tests/fitting/test_fit_manoeuvre.py's truths."""

import numpy as np

from velab.config import load_rig
from velab.fitting.prepare import CLOSURE_ROUNDS, RIVAL_DAIC
from velab.fitting.report import format_report
from velab.fitting.sections import fit_sections
from velab.moc import moc_head

# truth -> (J'_k, tau_k / T), T = 4L/a (tests/fitting/test_fit_truths.py's)
TRUTHS = {"S1": ((0.1,), (0.43,)), "S2": ((0.03, 0.15), (0.043, 1.3))}


def _stack_fit(truth: str, seed: int):
    rig = load_rig("perugia")
    J, rel = TRUTHS[truth]
    a = rig.nominal_wave_speed_m_s
    t = np.arange(-1000, 20000) / 1000.0
    h = moc_head(rig, a, np.array(J, dtype=float), np.array(rel, dtype=float) * 4 * rig.pipe.length_m / a, t)
    head = rig.steady_head_m + h + np.random.default_rng(seed).normal(0.0, 0.1, t.size)
    return a, fit_sections(t, {rig.head_section.name: head}, 0.0, rig, 20.0, record_rate_hz=1000.0)


def test_the_stacked_engine_takes_the_single_paths_closure_rules():
    """One place for each rule: the stacked engine's rounds and rival threshold are prepare's."""
    from velab.fitting import joint

    assert joint.CLOSURE_ROUNDS is CLOSURE_ROUNDS and joint.RIVAL_DAIC is RIVAL_DAIC


def test_the_closure_is_refined_again_with_the_named_models_wall():
    """S2 truth, seed 3: the first pass's best wall (white AIC) is S3's, the closure refined with it; the
    continuation names S2, so the closure is refined again with S2's wall and every model continued -- S2 named
    under its own closure, a within 2 SE, and the fit says so."""
    a, r = _stack_fit("S2", 3)
    assert r.best.name == "S2", format_report(r, elements=False)
    assert r.settings["manoeuvre"]["refined_with"] == "S2"
    assert any("refined again with the S2 wall" in n for n in r.notes), r.notes
    assert abs(r.best.wave_speed_m_s - a) <= 2.0 * r.best.wave_speed_se_m_s


def test_a_smaller_rival_is_compared_under_its_own_closure():
    """S1 truth, seed 4: under the closure refined with S2's wall S2 came out 0.3 AIC units ahead of S1 (a
    one-part stack named S2 before the stacked engine had the rival's comparison); under the closure refined
    with S1's own wall S1 is named and better than S2 under its own -- the single path's answer on this record
    too. The fit says so, the wave speed within 2 SE."""
    a, r = _stack_fit("S1", 4)
    assert r.best.name == "S1", format_report(r, elements=False)
    assert r.settings["manoeuvre"]["refined_with"] == "S1"
    assert any("S1 under the closure refined with its own wall is better than S2" in n for n in r.notes), r.notes
    assert abs(r.best.wave_speed_m_s - a) <= 2.0 * r.best.wave_speed_se_m_s
