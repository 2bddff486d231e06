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
