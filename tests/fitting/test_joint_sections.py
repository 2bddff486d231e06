"""A joint fit of runs with several transducers uses every section of every run (velab.fitting.joint on
velab.fitting.parts; issue 25 parts 1 and 2).

Data the fitter did not make: the time-domain model with the reference rig's real (butterfly, orifice-law)
valve on its sigmoid in position and quadratic friction, material A, sigma 0.1 m, the valve's head and a
head at 40 % of the pipe, at two steady flows, head only (each run's closure fitted); and runs written by
`velab synth` with a rig that has two transducers, fitted through the CLI.
"""

import json
from pathlib import Path

import pytest
from test_sections_fit import FS, W, two_section_record

from velab.cli import main
from velab.fitting.campaignrun import CampaignRun, head_sha256
from velab.fitting.joint import fit_joint
from velab.rig import Section
from velab.runfiles import read_run
from velab.fitting.report import format_report

FLOWS = (3.0, 4.2)  # l/s


def _run(q0_l_s: float, seed: int, mid_at: float = 0.4) -> CampaignRun:
    """One run of material A's pipe with two transducers (the valve's and one at 0.4 L: test_sections_fit's
    record at that flow); its rig file may say the mid one is at ``mid_at`` x L."""
    truth, t, heads = two_section_record(q0_l_s, seed)
    L = truth.pipe.length_m
    said = truth.with_changes(transducers=(Section("valve", L), Section("mid", mid_at * L)))
    return CampaignRun(f"run_{q0_l_s:g}", t, heads["valve"], 0.0, said, FS, None, head_sha256(t, heads["valve"]),
                       {"mid": heads["mid"]})


@pytest.fixture(scope="module")
def runs():
    return [_run(q, 50 + i) for i, q in enumerate(FLOWS)]


@pytest.fixture(scope="module")
def both(runs):
    return fit_joint(runs, W, models="2-4")


def test_a_joint_fit_uses_every_section_of_every_run(runs, both):
    """The true model and wave speed; one closure per run counted (not one per section); every section of
    every run reported at its own noise; and a more precise wall than the same runs' valve sections alone."""
    r = both
    assert r.best.name == "S3" and abs(r.best.wave_speed_m_s - 353.73) <= 0.5, format_report(r)
    # one closure per run (five parameters, two with its shape held at the rig's valve), not one per section
    closures = [x["manoeuvre"]["nuisance_parameters"] for x in r.runs]
    assert all(k in (2, 5) for k in closures) and r.settings["k_nuisance"] == sum(closures)
    assert r.best.k == 7 + r.settings["k_nuisance"] and r.settings["sections"] == 4
    assert r.best.n == 4 * int(W * FS)
    assert not [w for w in r.warnings if w["code"] == "misfit"], r.warnings
    for run in r.runs:
        secs = {s["name"]: s for s in run["sections"]}
        assert set(secs) == {"valve", "mid"} and secs["mid"]["position_m"] == pytest.approx(0.4 * 102.58)
        for s in secs.values():
            assert s["n"] == int(W * FS) and 0.8 < s["noise_ratio"] < 1.3 and not s["disagrees"], s
        assert run["n"] == 2 * int(W * FS) and not run["disagrees"]
        # the run's pooled ratio lies between its sections'
        assert min(s["noise_ratio"] for s in secs.values()) <= run["noise_ratio"] <= max(
            s["noise_ratio"] for s in secs.values())
        assert run["own"]["model"] == "S3" and abs(run["own"]["wave_speed"] - 353.73) <= 1.0
    valve_only = fit_joint([CampaignRun(s.path, s.time_s, s.head_m, 0.0, s.rig.with_changes(transducers=()),
                                        s.record_rate_hz, None, s.head_sha256) for s in runs], W, models="3")
    assert "sections" not in valve_only.runs[0] and valve_only.settings["sections"] == 2
    assert r.best.wave_speed_se_m_s < valve_only.best.wave_speed_se_m_s, (r.best.wave_speed_se_m_s,
                                                                          valve_only.best.wave_speed_se_m_s)


def test_a_section_that_disagrees_is_named_with_its_run(runs):
    """The second run's rig file puts its mid transducer at 0.6 L (it is at 0.4 L): that section, and so that
    run, disagrees, named by run and section; weighted by its own large F it does not drag the wall."""
    wrong = _run(FLOWS[1], 51, mid_at=0.6)
    r = fit_joint([runs[0], wrong], W, models="3")
    misfits = [w for w in r.warnings if w["code"] == "misfit"]
    assert [(w["run"], w["section"]) for w in misfits] == [(wrong.path, "mid")], r.warnings
    assert "section mid" in misfits[0]["message"] and wrong.path in misfits[0]["message"]
    assert [run["disagrees"] for run in r.runs] == [False, True]
    assert [s["disagrees"] for s in r.runs[1]["sections"]] == [False, True]
    assert abs(r.best.wave_speed_m_s - 353.73) <= 0.5


ROOT = Path(__file__).resolve().parents[2]
TWO = '\n[[transducers]]\nname = "valve"\nposition_m = 102.58\n\n[[transducers]]\nname = "mid"\nposition_m = 41.032\n'


def test_velab_fit_joint_of_synthetic_runs_with_two_transducers(tmp_path, capsys):
    """`velab synth` with a rig that has two transducers, at two flows: `velab fit --joint` fits both sections
    of both runs (JSON, the text table, the fit saved into each run, `velab info`)."""
    paths = []
    for i, q in enumerate(FLOWS):
        rig = tmp_path / f"two_{q:g}.toml"
        text = (ROOT / "configs" / "rigs" / "perugia.toml").read_text()
        rig.write_text(text.replace("steady_flow_m3_s = 3.64e-3", f"steady_flow_m3_s = {q / 1e3!r}") + TWO)
        out = tmp_path / f"two_{q:g}.h5"
        assert main(["synth", "--rig", str(rig), "--duration", str(W), "--seed", str(60 + i), "-o", str(out),
                     "-q"]) == 0
        paths.append(str(out))
    capsys.readouterr()
    assert main(["fit", *paths, "--joint", "--json", "--window", str(W), "--models", "2-4"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["settings"]["sections"] == 4 and doc["best"] in ("S3", "S4")
    for run in doc["runs"]:
        assert [s["name"] for s in run["sections"]] == ["valve", "mid"]
        assert all(0.8 < s["noise_ratio"] < 1.5 and not s["disagrees"] for s in run["sections"]), run["sections"]
    assert main(["fit", *paths, "--joint", "--window", str(W), "--models", "3", "--no-save"]) == 0
    text = capsys.readouterr().out
    assert text.count("section mid at 41.032 m") == 2 and text.count("section valve at 102.58 m") == 2
    assert main(["info", paths[0]]) == 0
    info = capsys.readouterr().out
    assert "joint fit joint_w6s: 2 runs" in info
    assert info.count("section mid at 41.032 m") == 2  # this run's and the other run's
    stored = read_run(paths[0])
    assert stored.rig.sections[1].name == "mid"
