"""A single record as a stack of one part names what the single path names (issue 51: one engine;
docs/decisions.md, "One engine: a single record as a stack of one part -- measured"): the two records on which
the one-part stack (velab.fitting.sections.fit_sections with the record's one head: velab.fitting.joint's
StackedSweep) had named another model than the single path (velab.fitting.entry.fit_record / fit_sweep), one
stacked fit each (benchmarks/one_engine.py fits both ways)."""

import math
from dataclasses import replace

import numpy as np

from velab.config import Material, load_rig
from velab.fitting.report import format_report
from velab.fitting.sections import fit_sections
from velab.synth import SynthSettings, synthesise, with_valve_law


def test_an_elastic_pipes_record_is_el_in_the_stack_as_in_the_single_path():
    """tests/fitting/test_fit_honesty.py's elastic pipe (80 m, 420 m/s, no creep), the imposed sigmoid fitted with
    the orifice rig file, seed 1, EL..S2: the single path names EL (S1 behind, its element on the lower tau bound a
    model error). The stack had named S1: its closure, refined first on the whole window from a wall calibrated
    under the early-window closure, made up for that wall's error (EL 8 in n ln F short). Refined first on the
    window's first part (the single path's lead window, velab.fitting.parts.Record.refine), EL is named."""
    rig = load_rig("perugia")
    rig = rig.with_changes(pipe=replace(rig.pipe, length_m=80.0), nominal_wave_speed_m_s=420.0)
    t, head, _, _ = synthesise(with_valve_law(rig, "imposed"), Material(wave_speed_m_s=420.0, elements=(),
                                                                         name="elastic"),
                               SynthSettings(seed=1, duration_s=20.0))
    r = fit_sections(t, {rig.head_section.name: head}, 0.0, rig, 20.0, record_rate_hz=1000.0, models=[0, 1, 2])
    b = r.best
    assert b.name == "EL" and b.support == "substantial", format_report(r, elements=False)
    assert r.settings["manoeuvre"]["refined_with"] == "EL"
    assert abs(b.wave_speed_m_s - 420.0) <= 2.0 * b.wave_speed_se_m_s
    # S1 is EL plus an element that is negligible or on the lower tau bound (a model error): no support for creep
    s1 = r["S1"]
    assert s1.equivalent_to == "EL" or s1.support == "model error", format_report(r, elements=False)


def test_the_imperial_rigs_s1_truth_is_s1_in_the_stack():
    """tests/fitting/test_fit_truths.py's S1 truth on the imperial rig (the rig's flow, nothing fitted): the
    single sweep names S1. The stack's S1 polish had stopped at its third time-domain refresh still gaining
    1,900 in n ln F, 10.7 short of the optimum, and S2 = S1 + a vanished element took those back and was named
    (joint.REFRESHES). Now S1 is named at its optimum: S2 gains nothing over it, its element within 2 SE of the
    truth."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from test_fit_truths import TRUTHS, _record

    rig = load_rig("imperial")
    t, h = _record(rig, "S1")
    r = fit_sections(t, {rig.head_section.name: rig.steady_head_m + h}, 0.0, rig, None, record_rate_hz=1000.0,
                     manoeuvre="rig")
    assert r.best.name == "S1", format_report(r, elements=False)
    s1, s2 = r["S1"], r["S2"]
    assert s1.n * math.log(s1.F) - s2.n * math.log(s2.F) < 0.5, format_report(r, elements=False)
    (el,) = s1.elements()
    J, rel = TRUTHS["S1"]
    tau_true = rel[0] * 4 * rig.pipe.length_m / rig.nominal_wave_speed_m_s
    assert abs(el["J_rel"] - J[0]) <= 2.0 * el["J_rel_se"]
    assert abs(el["tau"] - tau_true) <= 2.0 * el["tau_se"]
    assert np.isfinite(s1.wave_speed_se_m_s) and abs(s1.wave_speed_m_s - rig.nominal_wave_speed_m_s) <= 1.0
