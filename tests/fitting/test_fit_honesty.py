"""Honest on a valve its rig file does not describe (issue 51, item 6).

Records the fitter did not make: the time-domain model (MOC) with quadratic friction and the paper's imposed
sigmoid as the flow (``velab synth --valve imposed``: the flow itself is the sigmoid, no orifice law), sigma 0.1 m,
1 s pretrigger, 20 s at 1 kHz, fitted by default head-only (the closure fitted as nuisance parameters) with the
reference rig file, whose valve is a butterfly on the orifice law: not the record's. The fit has to find that
the rig's valve is not the record's (its shape and its law), and its wave speed's standard error has to cover
the truth; on an elastic pipe it has to name EL, not an element that takes up what the closure misses.
benchmarks/honesty.py prints the same over any number of seeds (docs/fitting.md, "A valve its rig file does not
describe").
"""

import math
from dataclasses import replace

import pytest

from velab.config import Material, load_material, load_rig
from velab.fitting.entry import fit_record
from velab.fitting.report import format_report
from velab.fitting.results import ModelFit
from velab.fitting.selection import MODEL_ERROR_SHARE, apply_criteria, model_error_elements
from velab.synth import SynthSettings, synthesise, with_valve_law

A_TRUE = 353.73


def _imposed_record(rig, material, seed):
    t, head, _, _ = synthesise(with_valve_law(rig, "imposed"), material, SynthSettings(seed=seed, duration_s=20.0))
    return t, head


@pytest.mark.parametrize("seed", [1, 2, 3, 4, 5, 6])
def test_imposed_sigmoid_with_the_orifice_rig_file_covers_the_wave_speed(seed):
    """Material A (S3): the truth within 2 standard errors of the best model's wave speed, S3 named or S4 with S3
    close behind (S4 by 1-6 AIC units on 2 of 12 seeds with the exact flow imposed and nothing fitted as well),
    F at the noise."""
    rig = load_rig("perugia")
    assert rig.valve.law == "orifice"
    t, head = _imposed_record(rig, load_material("A"), seed)
    r = fit_record(t, head, 0.0, rig, 20.0, record_rate_hz=1000.0)
    b = r.best
    assert r.settings["manoeuvre"]["source"] == "fitted" and r.settings["manoeuvre"]["shape"] == "fitted"
    z = (b.wave_speed_m_s - A_TRUE) / b.wave_speed_se_m_s
    assert abs(z) <= 2.0, format_report(r, elements=False)
    assert b.name == "S3" or (b.name == "S4" and r["S3"].delta_aic < 7), format_report(r, elements=False)
    assert b.noise_ratio < 1.2


def _elastic_rig():
    rig = load_rig("perugia")
    return rig.with_changes(pipe=replace(rig.pipe, length_m=80.0), nominal_wave_speed_m_s=420.0)


@pytest.mark.parametrize("seed", [2, 3])
def test_elastic_pipe_with_an_imposed_sigmoid_is_named_el(seed):
    """No creep (80 m, 420 m/s, quadratic friction), the imposed sigmoid, the orifice rig file: EL named with
    substantial support, a within 2 standard errors. Before: S1 by 40 AIC units on seed 1, its element on the lower
    tau bound (13.7 ms) holding 3.6e-5 of the compliance (the closure's refinement ended off the fit's optimum)."""
    rig = _elastic_rig()
    t, head = _imposed_record(rig, Material(wave_speed_m_s=420.0, elements=(), name="elastic"), seed)
    r = fit_record(t, head, 0.0, rig, 20.0, record_rate_hz=1000.0, models=[0, 1, 2])
    assert r.best.name == "EL" and r.best.support == "substantial", format_report(r, elements=False)
    assert abs(r.best.wave_speed_m_s - 420.0) <= 2.0 * r.best.wave_speed_se_m_s


def test_elastic_pipe_seed_1_reports_its_extra_element_as_a_model_error():
    """Seed 1: S1 fits best by 7 AIC units through an element on the lower tau bound holding ~2e-5 of the
    compliance (what the fitted closure leaves): reported as EL plus a negligible element, a model error, not as
    support for creep (velab.fitting.selection.mark_model_errors), with a warning that names it."""
    rig = _elastic_rig()
    t, head = _imposed_record(rig, Material(wave_speed_m_s=420.0, elements=(), name="elastic"), 1)
    r = fit_record(t, head, 0.0, rig, 20.0, record_rate_hz=1000.0, models=[0, 1, 2])
    b = r.best
    if b.name != "EL":
        assert b.support == "model error" and b.equivalent_to == "EL" and "model-error element" in b.note, format_report(r)
        assert b.model_error_elements == (0,)
        assert "model_error" in r.warning_codes() and "not the wall's creep" in format_report(r)
        # the model-averaged creep gives its weight to EL's (no creep): none is shown as the wall's
        assert r.creep_averaged().weights.get(b.name, 0.0) == 0.0
    assert abs(b.wave_speed_m_s - 420.0) <= 2.0 * b.wave_speed_se_m_s


def _fit(name, m, J_rel, tau, aic):
    E = tuple(1e9 / j for j in J_rel)
    return ModelFit(name=name, m=m, k=2 * m + 1, reduced=False, n=1000, F=math.exp(aic / 1000), wave_speed_m_s=420.0,
                    E_pa=E, eta_pa_s=tuple(e * t for e, t in zip(E, tau)), lag1_autocorr=0.0, J_rel=tuple(J_rel))


def test_the_model_error_rule_flags_only_a_negligible_element_on_a_bound():
    lo, hi = 0.0137, 10.0
    on_bound = _fit("S1", 1, [0.5 * MODEL_ERROR_SHARE], [0.016], -10.0)
    assert model_error_elements(on_bound, lo, hi) == [0]
    # a real fast element (material A's: 19 ms, 3e-3 of the compliance) and a tiny one off the bounds are creep
    assert model_error_elements(_fit("S1", 1, [3e-3], [0.0193], 0.0), lo, hi) == []
    assert model_error_elements(_fit("S1", 1, [0.5 * MODEL_ERROR_SHARE], [0.2], 0.0), lo, hi) == []
    el = _fit("EL", 0, [], [], 0.0)
    fits = [el, on_bound]
    apply_criteria(fits, "white", (lo, hi))
    assert on_bound.support == "model error" and on_bound.equivalent_to == "EL"
    assert on_bound.model_error_elements == (0,) and el.model_error_elements == ()
    assert on_bound.note == "S1 = EL + a model-error element"
