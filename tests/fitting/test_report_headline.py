"""The result first (issue 50): the Headline of a fit and the text report that opens with it.

The results here are built by hand (ModelFits ranked by velab.fitting.results.apply_criteria), so every
number the headline shows is known; tests/commands/test_report_cli.py runs the commands on real fits.
"""

from __future__ import annotations

import math

import pytest

from velab.fitting.headline import Headline, headline, headline_lines
from velab.fitting.report import format_report
from velab.fitting.results import ModelFit, SweepResult
from velab.fitting.selection import apply_criteria


def _fit(name, m, F, a, E=(), eta=(), se=0.01, negligible=None, noise=1.0e-4):
    n = 20000
    E = tuple(E)
    return ModelFit(
        name=name, m=m, k=2 * m + 1, reduced=False, n=n, F=F, wave_speed_m_s=a, E_pa=E, eta_pa_s=tuple(eta),
        lag1_autocorr=0.3, wave_speed_se_m_s=0.05, E_se_pa=tuple(se * e for e in E),
        eta_se_pa_s=tuple(se * h for h in eta), tau_se_s=tuple(2 * se * h / e for e, h in zip(E, eta)),
        J_rel=tuple(0.1 for _ in E), J_rel_se=tuple(0.001 for _ in E),
        negligible=tuple(negligible or (False,) * m), element_gain=tuple(50.0 for _ in E), noise_ratio=F / noise,
    )


def _result(misfit=False) -> SweepResult:
    noise = 1.0e-4
    scale = 3.0 if misfit else 1.0
    models = [
        _fit("EL", 0, 9e-4 * scale, 340.0),
        _fit("S1", 1, 2e-4 * scale, 350.0, [5e9], [5e9]),
        _fit("S2", 2, 1.05e-4 * scale, 353.73, [4.5e10, 4.6e9], [9.0e9, 9.0e9]),
        _fit("S3", 3, 1.0499e-4 * scale, 353.74, [4e11, 4.5e10, 4.6e9], [8e9, 9.0e9, 9.0e9],
             negligible=(True, False, False)),
    ]
    apply_criteria(models, "ar1")
    warnings = []
    if misfit:
        warnings.append({"code": "misfit", "message": "the best model S2 leaves residuals 3.2x the record's noise "
                         "(mean square: F = 3.15e-04 m^2 against the pretrigger baseline's 1e-04 m^2; chance allows "
                         "1.50x): its parameters are not the pipe's; check the rig, the valve, air, friction"})
    return SweepResult(n=20000, window_s=20.0, sample_rate_hz=1000.0, method="least-squares",
                       settings={"bounds": {}}, models=models, baseline_noise_m=math.sqrt(noise), baseline_lag1=0.1,
                       adequacy={"misfit_bound": 1.5, "baseline_samples": 2000}, warnings=warnings)


def test_the_headline_names_the_best_model_its_support_and_every_element():
    r = _result()
    h = headline(r)
    assert isinstance(h, Headline) and h.best_model == r.best.name == "S2"
    assert h.wave_speed_m_s == pytest.approx(353.73) and h.wave_speed_se_m_s == pytest.approx(0.05)
    assert [e.E_pa for e in h.elements] == list(r.best.E_pa)
    assert [e.tau_s for e in h.elements] == pytest.approx([0.2, 9.0 / 4.6])
    assert [e.J_per_pa for e in h.elements] == pytest.approx([1 / 4.5e10, 1 / 4.6e9])
    assert h.elements[0].E_se_pa == pytest.approx(0.01 * 4.5e10)
    assert h.noise_ratio == pytest.approx(1.05) and not h.misfit and h.warnings == ()
    assert "next S3" in h.support and f"Akaike weight {r.best.weight:.2f}" in h.support
    lines = headline_lines(h)
    assert lines[0] == "RESULT (fit): best model S2"
    text = "\n".join(lines)
    assert "a = 353.73 +- 0.05 m/s" in text
    for e in h.elements:  # every element's E, eta, tau, J with its standard error
        assert f"{e.E_pa:.3e} +- {e.E_se_pa:.2g}" in text and f"{e.eta_pa_s:.3e} +- {e.eta_se_pa_s:.2g}" in text
        assert f"{e.tau_s:.4g} +- {e.tau_se_s:.2g}" in text and f"{e.J_per_pa:.3e} +- {e.J_se_per_pa:.2g}" in text
    assert "1.05x the record's own noise (chance allows up to 1.50x)" in text
    d = h.to_dict()
    assert d["best_model"] == "S2" and len(d["elements"]) == 2 and d["misfit"] is False


def test_a_misfit_is_said_in_words_and_every_line_fits_the_width():
    h = headline(_result(misfit=True))
    assert h.misfit and h.warnings[0].startswith("misfit: the best model S2")
    for width in (100, 80, 60):
        lines = headline_lines(h, width)
        assert max(map(len, lines)) <= width, (width, lines)
        text = " ".join(line.strip() for line in lines)
        assert "does not describe the record (misfit)" in text and "WARNING misfit: the best model S2" in text
        assert "above the 1.50x chance allows" in text
    # narrower than the element table: each element on lines of its own, nothing lost
    narrow = " ".join(line.strip() for line in headline_lines(h, 80))
    assert narrow.count("KV ") == 2 and "tau 0.2 +- 0.004 s" in narrow


def test_a_negligible_element_and_an_elastic_wall_are_named():
    r = _result()
    h = headline(SweepResult(**{**r.__dict__, "models": r.models[:1] + r.models[3:]}))
    assert h.best_model in ("EL", "S3")
    s3 = headline(SweepResult(**{**r.__dict__, "models": [r.models[3]]}))
    assert s3.support == "the only model fitted; negligible element"
    assert any("negligible element" in line for line in headline_lines(s3))
    el = headline(SweepResult(**{**r.__dict__, "models": [r.models[0]]}))
    assert el.elements == () and any("elastic wall" in line for line in headline_lines(el))


def test_a_fit_read_back_gives_the_same_headline():
    r = _result()
    back = SweepResult.from_dict(r.to_dict())
    assert headline_lines(headline(back)) == headline_lines(headline(r))


def test_the_default_report_opens_with_the_headline_and_fits_100_columns():
    r = _result(misfit=True)
    r.notes.append("not saved: the run is still open for writing (" + "x" * 150 + ")")
    text = format_report(r, verbose=False)
    lines = text.splitlines()
    assert lines[:len(headline_lines(headline(r)))] == headline_lines(headline(r))
    assert max(map(len, lines)) <= 100, max(lines, key=len)
    assert "not saved" in text  # a note is never hidden, only wrapped
    # the detail only with -v: the AR(1) and white AIC, n_eff, lag-1, J_rel
    for detail in ("AIC AR1", "n_eff", "J_rel", "lag-1"):
        assert detail not in text
    full = format_report(r, verbose=True)
    assert full.startswith(text.split("\n")[0]) and "AIC AR1" in full and "n_eff" in full and "J_rel" in full
