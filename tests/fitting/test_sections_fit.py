"""A record with two sections (the valve and 40 % of the length) fitted with both: data from the time-domain
model with the real (butterfly, orifice-law) valve and quadratic friction, sigma 0.1 m, head only (the
closure fitted), which the fitter did not make."""

import json

import numpy as np
import pytest

from velab.config import load_material, load_rig
from velab.errors import DataError
from velab.fitting.entry import fit_record
from velab.fitting.sections import fit_sections
from velab.model import creep_scale
from velab.moc import moc_head
from velab.rig import Section
from velab.valvelaw import commanded_position_pct
from velab.fitting.report import format_report

W = 6.0
FS = 1000.0


def two_section_record(q0_l_s: float | None = None, seed: int = 7):
    """(rig, t, heads) of material A's pipe with a transducer at the valve and one at 0.4 L (the rig at
    ``q0_l_s``, its own Q0 if None): the time-domain model, the real valve on its sigmoid in position,
    quadratic friction, sigma 0.1 m on each head (tests/fitting/test_joint_sections.py takes it too)."""
    A = load_material("A")
    base = load_rig("perugia")
    if q0_l_s is not None:
        base = base.with_changes(steady_flow_m3_s=q0_l_s / 1e3)
    L = base.pipe.length_m
    rig = base.with_changes(transducers=(Section("valve", L), Section("mid", 0.4 * L)))
    a = A.wave_speed_m_s
    J = creep_scale(rig, a) * np.array([e.J_per_pa for e in A.elements])
    tau = np.array([e.tau_s for e in A.elements])
    t = np.arange(-int(0.6 * FS), int((W + 0.1) * FS)) / FS
    m = rig.manoeuvre
    hs = moc_head(rig, a, J, tau, t, position=lambda x: commanded_position_pct(x, m.beta_per_s, m.gamma),
                  sections_m=(L, 0.4 * L))
    rng = np.random.default_rng(seed)
    heads = {"valve": rig.steady_head_m + hs[0] + rng.normal(0, 0.1, t.size),
             "mid": rig.steady_head_at_m(0.4 * L) + hs[1] + rng.normal(0, 0.1, t.size)}
    return rig, t, heads


@pytest.fixture(scope="module")
def record():
    return two_section_record()


@pytest.fixture(scope="module")
def both(record):
    rig, t, heads = record
    return fit_sections(t, heads, 0.0, rig, W, record_rate_hz=FS, models="1-4")


def test_two_sections_give_the_true_model_and_a_smaller_se(record, both):
    rig, t, heads = record
    r = both
    assert r.best.name == "S3" and abs(r.best.wave_speed_m_s - 353.73) <= 0.5, format_report(r)
    valve = fit_record(t, heads["valve"], 0.0, rig.with_changes(transducers=()), W, record_rate_hz=FS, models="1-4")
    s3 = next(f for f in valve.models if f.name == "S3")
    # measured: 0.022 m/s with both sections, 0.044 (S3) at the valve alone
    assert r.best.wave_speed_se_m_s < s3.wave_speed_se_m_s
    # one closure for both sections (five parameters, two with its shape held at the rig's valve)
    assert r.settings["k_nuisance"] == r.settings["manoeuvre"]["nuisance_parameters"] in (2, 5)
    assert r.best.k == 7 + r.settings["k_nuisance"]
    assert not r.warnings


def test_each_section_is_reported(both):
    d = json.loads(json.dumps(both.to_dict()))
    secs = {s["name"]: s for s in d["sections"]}
    assert set(secs) == {"valve", "mid"}
    assert secs["mid"]["position_m"] == pytest.approx(0.4 * 102.58)
    for s in secs.values():
        assert s["n"] == int(W * FS) and 0.8 < s["noise_ratio"] < 1.5 and not s["disagrees"]


def test_a_transducer_at_the_wrong_position_is_named(record):
    rig, t, heads = record
    L = rig.pipe.length_m
    wrong = rig.with_changes(transducers=(Section("valve", L), Section("mid", 0.6 * L)))
    r = fit_sections(t, heads, 0.0, wrong, W, record_rate_hz=FS, models="3")
    secs = {s["name"]: s for s in r.sections}
    assert secs["mid"]["disagrees"] and not secs["valve"]["disagrees"]
    assert [w["section"] for w in r.warnings if w["code"] == "misfit"] == ["mid"]
    assert abs(r.best.wave_speed_m_s - 353.73) <= 0.5  # weighted by its own misfit, it cannot drag the wall


def test_heads_must_match_the_rig_sections(record):
    rig, t, heads = record
    with pytest.raises(DataError, match="no head for mid"):
        fit_sections(t, {"valve": heads["valve"]}, 0.0, rig, W, record_rate_hz=FS, models="1")
    with pytest.raises(DataError, match="no transducer named H3"):
        fit_sections(t, {**heads, "H3": heads["mid"]}, 0.0, rig, W, record_rate_hz=FS, models="1")
    L = rig.pipe.length_m
    off = rig.with_changes(transducers=(Section("up", 0.2 * L), Section("mid", 0.4 * L)))
    with pytest.raises(DataError, match="no transducer at the valve"):
        fit_sections(t, {"up": heads["valve"], "mid": heads["mid"]}, 0.0, off, W, record_rate_hz=FS, models="1")
