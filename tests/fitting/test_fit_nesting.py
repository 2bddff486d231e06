"""A model that contains another never fits worse (issue 15): F(EL) >= F(S1) >= ... >= F(S6).

Every S(m) contains S(m-1) (an element whose compliance vanishes) and EL; the reduced
S(m)r contain S(m-1)r. The fitter guarantees the order to a relative 1e-9 for every
method, with and without the full-band polish, whatever the data.
"""

import json
import math
import os

import numpy as np

from velab.fitting.selection import ELEMENT_PRICE
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from velab.cli import main
from velab.config import KelvinVoigt, Material, load_rig
from velab.fitting import METHODS, fit_sweep
from velab.model import creep_scale, valve_head
from velab.fitting.report import format_report

REL = 1e-9
# a fixed (derandomised) sample of cases per method, scaled with the suite's VELAB_FUZZ_EXAMPLES (tests/conftest.py)
# for a longer local run: 8 + 8 + 5 + 3 in the default suite. As one test over a sampled method, 16 of its 37
# cases were Nelder-Mead (15 of its 21 s: a simplex case costs 1-3 s, a least-squares one 0.3 s) and how many
# were evolution was chance; per method, each method has its own sample and the four tests spread over the processes
_N = int(os.environ.get("VELAB_FUZZ_EXAMPLES", "150"))
NESTING_EXAMPLES = {"auto": max(6, _N // 18), "least-squares": max(6, _N // 18),
                    "nelder-mead": max(4, _N // 30), "evolution": max(3, _N // 50)}
PERUGIA = load_rig("perugia").with_changes(friction="linear")


def _rig(kind: int):
    """The reference rig and variants with another length, bore, flow and closure."""
    if kind == 0:
        return PERUGIA
    from dataclasses import replace

    p = PERUGIA.pipe
    if kind == 1:  # a long small-bore coil, faster closure (after the Imperial College rig)
        return PERUGIA.with_changes(
            pipe=replace(p, length_m=277.0, inner_diameter_m=0.0506, wall_thickness_m=0.0062),
            steady_flow_m3_s=1.0e-3, nominal_wave_speed_m_s=395.0,
            manoeuvre=replace(PERUGIA.manoeuvre, beta_per_s=40.0, gamma=-5.0))
    return PERUGIA.with_changes(pipe=replace(p, length_m=55.0), steady_flow_m3_s=2.0e-3)


def _chain_ok(fits):
    """Every fitted model is no worse than each smaller model of its family (and EL)."""
    bad = []
    full = sorted((f for f in fits if not f.reduced), key=lambda f: f.m)
    red = sorted((f for f in fits if f.reduced or f.m == 0), key=lambda f: f.m)
    for chain in (full, red):
        for i, f in enumerate(chain):
            for g in chain[:i]:
                if f.F > g.F * (1 + REL):
                    bad.append((f.name, f.F, g.name, g.F))
    return bad


materials = st.one_of(
    st.just([]),  # elastic
    st.lists(st.tuples(st.floats(-4.0, 0.0), st.floats(math.log10(0.02), math.log10(5.0))), min_size=1, max_size=3),
)


_CASE = dict(
    elements=materials,
    rig_kind=st.integers(0, 2),
    noise=st.sampled_from([0.01, 0.05, 0.1, 0.3]),
    m_lo=st.integers(0, 5),
    n_models=st.integers(2, 3),
    reduced=st.booleans(),
    polish=st.booleans(),
    seed=st.integers(0, 2**16),
)


def _nesting_test(method: str):
    def test(elements, rig_kind, noise, m_lo, n_models, reduced, polish, seed):
        _check_nesting(elements, rig_kind, noise, m_lo, n_models, method, reduced, polish, seed)

    # its own name: hypothesis derives the derandomised cases from it, so each method gets its own sample
    test.__name__ = test.__qualname__ = "test_larger_models_never_fit_worse_" + method.replace("-", "_")
    test.__doc__ = f"F(larger) <= F(smaller) * (1 + REL) in every family, fitted by {method}."
    return settings(max_examples=NESTING_EXAMPLES[method], deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])(given(**_CASE)(test))


test_larger_models_never_fit_worse_auto = _nesting_test("auto")
test_larger_models_never_fit_worse_least_squares = _nesting_test("least-squares")
test_larger_models_never_fit_worse_nelder_mead = _nesting_test("nelder-mead")
test_larger_models_never_fit_worse_evolution = _nesting_test("evolution")


def test_every_method_has_a_nesting_test():
    assert set(NESTING_EXAMPLES) == set(METHODS)


def _check_nesting(elements, rig_kind, noise, m_lo, n_models, method, reduced, polish, seed):
    rig = _rig(rig_kind)
    a = rig.nominal_wave_speed_m_s
    c = creep_scale(rig, a)
    mat = Material(a, tuple(KelvinVoigt.from_creep(10**lj / c, 10**lt) for lj, lt in elements))
    # short, coarse records keep each case to a fraction of a second
    t = np.arange(-50, 450) / 200.0
    h = valve_head(t, rig, mat) + np.random.default_rng(seed).normal(0, noise, t.size)
    if method in ("nelder-mead", "evolution"):
        # the simplex and the global search cost 10-50 x more per model: two small models
        m_lo, n_models = min(m_lo, 2 if method == "nelder-mead" else 1), 2
    models = list(range(m_lo, min(m_lo + n_models, 7)))
    if len(models) < 2:
        models = [m_lo - 1, m_lo]
    r = fit_sweep(t, h, rig, models=models, window_s=2.25, method=method, reduced=reduced, polish=polish,
                  starts=2 if method != "least-squares" else None, threads=1)
    assert not _chain_ok(r.models), (_chain_ok(r.models), format_report(r, elements=False))
    for f in r.models:
        assert math.isfinite(f.F) and f.F > 0
        assert len(f.negligible) == f.m == len(f.E_pa)
        if f.equivalent_to:  # a model named as a smaller one really has vanished or split elements, or elements
            # the selection reports as model errors (velab.fitting.selection.mark_model_errors)
            assert any(f.negligible) or f.split_elements or f.model_error_elements


def test_elastic_pipe_table(tmp_path, capsys):
    """Issue 15's record: EL best, every Sk at most 4k + 1 AIC units behind EL (its parameter
    penalty plus chance), not thousands; where an element vanished the table says so."""
    run = tmp_path / "el.h5"
    assert main(["synth", "--material", "elastic", "-o", str(run)]) == 0
    capsys.readouterr()
    assert main(["fit", str(run), "--no-save", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    by = {m["name"]: m for m in doc["models"]}
    assert doc["best"] == "EL"
    for k in range(1, 7):
        f = by[f"S{k}"]
        assert f["delta_aic"] <= 4 * k + 1, (f["name"], f["delta_aic"])
        assert f["delta_aic_white"] <= 4 * k + 1, (f["name"], f["delta_aic_white"])
        assert f["F"] <= by[f"S{k - 1}" if k > 1 else "EL"]["F"] * (1 + REL)
        assert abs(f["wave_speed"] - 353.73) < 0.5
        for el in f["elements"]:
            if el["negligible"]:
                assert el["gain"] < 0.1
        if f["equivalent_to"]:
            assert f["note"].startswith(f"S{k} = {f['equivalent_to']} + ")


def test_reduced_models_nest():
    """The reduced S(m)r (tau fixed at 0.01, 0.1, 1, 10, 100 s) contain S(m-1)r: with the paper's
    bounds S4r and S5r fitted worse than S3r (the 10 s and 100 s elements could not vanish)."""
    rig = PERUGIA
    t = np.arange(8000) / 1000.0
    from velab.config import load_material

    h = valve_head(t, rig, load_material("A")) + np.random.default_rng(1).normal(0, 0.1, t.size)
    r = fit_sweep(t, h, rig, models=range(0, 6), window_s=8.0, reduced=True)
    F = {f.name: f.F for f in r.models}
    for m in range(1, 6):
        prev = "EL" if m == 1 else f"S{m - 1}r"
        assert F[f"S{m}r"] <= F[prev] * (1 + REL), (m, F)
    s5 = r["S5r"]
    assert any(s5.negligible) or F["S5r"] < F["S4r"]
    if any(s5.negligible):
        assert "negligible" in s5.note


def test_models_past_the_first_element_that_does_not_pay_are_not_searched(monkeypatch):
    """Forward selection stops at the first element that does not pay its AIC price (n ln F < 4):
    on a two-element truth S3 does not, so S4 and S5 are S3 plus vanished elements, not searched.
    A search of S4 and S5 (the rule switched off) finds nothing that changes the AIC table at the
    precision it is reported to (0.01), nor the best model."""
    from velab.fitting import sweep

    truth = Material(353.7, (KelvinVoigt(4.0e10, 4.0e10 * 0.05), KelvinVoigt(5.0e10, 5.0e10 * 1.5)), "two")
    t = np.arange(20000) / 1000.0
    h = valve_head(t, PERUGIA, truth) + np.random.default_rng(7).normal(0.0, 0.05, t.size)
    r = fit_sweep(t, h, PERUGIA, models=range(6))
    gain = r.n * math.log(r["S2"].F / r["S3"].F)
    assert gain < ELEMENT_PRICE
    assert r.settings["not_searched"] == ["S4", "S5"]
    assert r["S4"].equivalent_to == "S3" and r["S5"].equivalent_to == "S3"
    assert r["S4"].starts == 0 and r["S5"].evaluations < 20
    assert any("S4, S5: not searched" in note for note in r.notes)
    assert not _chain_ok(r.models)

    monkeypatch.setattr(sweep, "NOTHING_LEFT", False)
    searched = fit_sweep(t, h, PERUGIA, models=range(6))
    assert searched.settings["not_searched"] == []
    assert searched.best.name == r.best.name == "S2"
    for a, b in zip(r.models, searched.models):
        assert abs(a.aic - b.aic) < 0.01, (a.name, a.aic, b.aic)
    assert searched.evaluations > r.evaluations + 500
