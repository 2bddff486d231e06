"""A record's fit through the stacked engine (velab.fitting.recordfit): what its result says of the models the
sweep did not continue after the closure's refinement is said by their names, in the settings and the notes."""

import sys
from pathlib import Path

from velab.config import load_material, load_rig
from velab.fitting.entry import fit_record
from velab.fitting.report import format_report

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_fit_honesty import _imposed_record  # noqa: E402


def test_the_models_not_continued_are_named_in_the_settings_and_a_note():
    """Material A's imposed sigmoid, head only (the closure fitted and refined), EL..S3 on 8 s: EL and S1 are far
    behind S3 after the refinement and are not polished again; the settings and the note name them as the result's
    models are named (the sweep keys them (m, reduced))."""
    rig = load_rig("perugia")
    t, head = _imposed_record(rig, load_material("A"), 1)
    r = fit_record(t, head, 0.0, rig, 8.0, record_rate_hz=1000.0, models=[0, 1, 2, 3])
    names = [f.name for f in r.models]
    skipped = r.settings["not_continued"]
    assert skipped and set(skipped) <= set(names) and "EL" in skipped, (skipped, format_report(r, elements=False))
    (note,) = [n for n in r.notes if "not polished again" in n]
    assert note.startswith(", ".join(skipped) + ": not polished again after the closure's refinement"), note


def test_the_result_counts_the_stacked_models_evaluations():
    """The stacked engine counts its evaluations over the whole sweep (the forks of the coarse starts' race added
    back): a record's fit says how many it took, more for more models, the same on a second fit of the same
    record, and its JSON carries the count."""
    rig = load_rig("perugia")
    t, head = _imposed_record(rig, load_material("A"), 1)
    one = fit_record(t, head, 0.0, rig, 4.0, record_rate_hz=1000.0, models=[0])
    three = fit_record(t, head, 0.0, rig, 4.0, record_rate_hz=1000.0, models=[0, 1, 2])
    again = fit_record(t, head, 0.0, rig, 4.0, record_rate_hz=1000.0, models=[0, 1, 2])
    assert 0 < one.evaluations < three.evaluations, (one.evaluations, three.evaluations)
    assert again.evaluations == three.evaluations
    assert three.to_dict()["evaluations"] == three.evaluations


def test_a_stacked_evaluators_fork_counts_apart_and_is_added_back():
    """A fork of a stacked evaluator (one per thread of the starts' race) counts on its own; the sweep's count
    grows by what fan_out adds back, not by the fork's evaluations as they happen."""
    import numpy as np

    from velab.fitting.engine import HeadEvaluator
    from velab.fitting.stacked import Count, StackedEvaluator
    from velab.fitting.starts import fan_out
    from velab.fitting.solvers import Stage

    rig = load_rig("perugia")
    ev = HeadEvaluator(rig, np.arange(0, 2000) * 1e-3)
    total = Count()
    st = StackedEvaluator([ev], [1.0], total)
    stage = Stage(st, np.zeros(st.n_t))
    a = rig.nominal_wave_speed_m_s
    during = fan_out(stage, lambda s, _: (s.ev.head(a, [], []), total.evaluations)[1], [0, 1, 2, 3], parallel=True)
    assert during == [0, 0, 0, 0]  # the forks' evaluations are not the sweep's until the race has ended
    assert total.evaluations == st.evaluations == 4 and total.jacobians == 0
    st.head_jac_x(a, [], [])
    assert (total.evaluations, total.jacobians) == (5, 1)
