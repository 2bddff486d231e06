"""The stacked engine takes the single sweep's search options (issue 51: every method and option available to all):
``method`` least-squares / nelder-mead / evolution, ``starts`` = N and ``polish`` = False on a record's two sections
(velab.fitting.sections.fit_sections) and on a campaign of two runs (velab.fitting.joint.fit_joint). Short windows
and EL..S2 (tests/fitting/test_sections_fit.py's record: the time-domain model with the real valve and quadratic
friction, sigma 0.1 m, the closure fitted): the nesting order holds, the settings say the search, and a search that
is not the default names the default's model on these easy records. The reduced models: test_stack_reduced.py."""

import pytest
from test_sections_fit import FS, two_section_record

import velab.fitting.joint as joint
from velab.fitting.campaignrun import CampaignRun, head_sha256
from velab.fitting.joint import fit_joint
from velab.fitting.report import format_report
from velab.fitting.sections import fit_sections

W = 4.0
MODELS = [0, 1, 2]


@pytest.fixture(scope="module")
def record():
    return two_section_record()


@pytest.fixture(scope="module")
def runs():
    """Two single-section runs of material A's pipe at two flows (their valve heads)."""
    out = []
    for i, q in enumerate((3.0, 4.2)):
        rig, t, heads = two_section_record(q, 50 + i)
        rig = rig.with_changes(transducers=())
        out.append(CampaignRun(f"run_{q:g}", t, heads["valve"], 0.0, rig, FS, None, head_sha256(t, heads["valve"])))
    return out


def _sections(record, **choices):
    rig, t, heads = record
    return fit_sections(t, heads, 0.0, rig, W, record_rate_hz=FS, models=MODELS, threads=1, **choices)


def _campaign(runs, **choices):
    return fit_joint(runs, W, models=MODELS, threads=1, **choices)


FITS = {"sections": _sections, "campaign": _campaign}


@pytest.fixture(scope="module")
def defaults(record, runs):
    return {"sections": _sections(record), "campaign": _campaign(runs)}


def _nested(r):
    Fs = [r[n].F for n in ("EL", "S1", "S2")]
    assert Fs[0] >= Fs[1] * (1 - 1e-9) and Fs[1] >= Fs[2] * (1 - 1e-9), (Fs, format_report(r, elements=False))


CASES = [
    ("sections", dict(starts=2)),
    ("campaign", dict(starts=2)),
    ("sections", dict(method="least-squares")),
    ("campaign", dict(method="least-squares")),
    # (the simplex and the evolution from a few starts: from every one, S1 and S2 take 7 s on the sections)
    ("sections", dict(method="nelder-mead", starts=3)),
    ("campaign", dict(method="nelder-mead", starts=2)),
    ("sections", dict(method="evolution", starts=2)),
    ("campaign", dict(method="evolution", starts=2)),
]


@pytest.mark.parametrize("kind, choices", CASES, ids=[f"{k}-{'-'.join(f'{a}={b}' for a, b in c.items())}"
                                                      for k, c in CASES])
def test_a_stacked_fit_searches_as_asked(kind, choices, record, runs, defaults, monkeypatch):
    """Each coarse search gets the method and at most the starts asked for (least-squares: one); the settings and
    notes say so; F(EL) >= F(S1) >= F(S2); the model named is the default search's, its F within 1e-6."""
    seen = []
    real = joint.coarse_search

    def spy(stage, pm, starts, method, seed, max_nfev, parallel=False):
        seen.append((pm.m, len(starts), method, seed))
        return real(stage, pm, starts, method, seed, max_nfev, parallel)

    monkeypatch.setattr(joint, "coarse_search", spy)
    r = FITS[kind](record if kind == "sections" else runs, **choices)
    method = choices.get("method", "auto")
    cap = 1 if method == "least-squares" else choices.get("starts")
    assert [m for m, *_ in seen] == [1, 2] and all(ms == method and seed == m for m, _, ms, seed in seen), seen
    assert all(n <= cap for _, n, _, _ in seen if cap is not None), seen
    s = r.settings
    assert (s["method"], s["starts"], s["polish"], s["reduced"]) == (method, cap, True, False), s.to_dict()
    assert s["sections" if kind == "sections" else "joint"]
    assert r.method == ("sections" if kind == "sections" else "joint")
    if method != "auto":
        assert any(n.startswith(f"method {method}:") for n in r.notes), r.notes
    if cap is not None and method != "least-squares":
        assert f"at most {cap} coarse starts a model" in r.notes, r.notes
    _nested(r)
    d = defaults[kind]
    assert r.best.name == d.best.name == "S2", format_report(r, elements=False)
    assert r.best.F == pytest.approx(d.best.F, rel=1e-6)


@pytest.mark.parametrize("kind", ["sections", "campaign"])
def test_a_stacked_fit_without_the_polish(kind, record, runs, defaults):
    """polish=False: the walls fitted on the coarse grids; the settings say no polish, the notes what F then is;
    the nesting order holds and F is near the polished fit's."""
    r = FITS[kind](record if kind == "sections" else runs, polish=False)
    assert r.settings["polish"] is False and r.settings["method"] == "auto"
    assert any(n.startswith("no polish:") and "decimated by" in n and "every sample" in n for n in r.notes), r.notes
    _nested(r)
    d = defaults[kind]
    assert r.best.name == d.best.name
    for name in ("EL", "S1", "S2"):
        assert r[name].F == pytest.approx(d[name].F, rel=1e-3)
    if kind == "campaign":  # each run's own wall (polished from the joint wall on the coarse grids too)
        for run, run_d in zip(r.runs, d.runs):
            assert run["own"]["F"] == pytest.approx(run_d["own"]["F"], rel=1e-3), (run["own"], run_d["own"])

