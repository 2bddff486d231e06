"""Fit groups: stored from to_dict() whatever its fields, read back tolerant of missing and extra fields."""

from __future__ import annotations

import json
import math
import shutil

import h5py
import numpy as np
import pytest

from velab.cli import main
from velab.fitting.results import ModelFit, SweepResult
from velab.fitting.selection import apply_criteria
from velab.runfiles import open_run_file, read_fit_dict, read_fit_group, read_run, save_fit


@pytest.fixture(scope="module")
def run_file(tmp_path_factory):
    p = tmp_path_factory.mktemp("fits") / "a.h5"
    assert main(["synth", "--duration", "2", "-o", str(p)]) == 0
    return p


def _result() -> SweepResult:
    fits = [ModelFit("EL", 0, 1, False, 1000, 0.9, 349.0, (), (), 0.97),
            ModelFit("S1", 1, 3, False, 1000, 0.01, 352.9, (8.7e9,), (4.9e9,), 0.4)]
    apply_criteria(fits)
    return SweepResult(n=1000, window_s=1.0, sample_rate_hz=1000.0, method="auto", settings={"models": [0, 1]},
                       models=fits, notes=["a note é"])


def test_round_trip_of_a_sweep(run_file, tmp_path):
    p = tmp_path / "a.h5"
    shutil.copy(run_file, p)
    r = _result()
    assert save_fit(p, r, "x") == "x"
    with open_run_file(p) as fh:
        back = read_fit_group(fh["entry/fits/x"])
    assert [f.name for f in back.models] == ["EL", "S1"]
    assert back.best.name == r.best.name and back.window_s == 1.0 and back.notes == ["a note é"]
    s1 = back["S1"]
    assert s1.E_pa == (8.7e9,) and s1.eta_pa_s == (4.9e9,) and s1.aic == pytest.approx(r["S1"].aic)
    assert s1.support == r["S1"].support and s1.lag1_autocorr == 0.4
    assert back.settings == {"models": [0, 1]}


def test_fields_the_fitter_adds_are_stored_without_the_store_knowing_them(run_file, tmp_path):
    p = tmp_path / "a.h5"
    shutil.copy(run_file, p)
    d = _result().to_dict()
    d["effective_sample_size"] = 412.5
    d["models"][1] |= {"bounds_hit": ["tau1"], "uncertainty": {"wave_speed": 0.31, "E": [1e8]},
                       "aic_ar1": -512.25, "converged": True}
    save_fit(p, d, "new")
    with open_run_file(p) as fh:
        g = fh["entry/fits/new"]
        assert g["S1/uncertainty/wave_speed"].attrs["units"] == "m/s"
        back = read_fit_dict(g)
        sweep = read_fit_group(g)  # the result classes ignore what they do not know
    assert back["effective_sample_size"] == 412.5
    s1 = back["models"][1]
    assert s1["bounds_hit"] == ["tau1"] and s1["uncertainty"] == {"wave_speed": 0.31, "E": [1e8]}
    assert s1["aic_ar1"] == -512.25 and s1["converged"] is True
    assert sweep["S1"].wave_speed_m_s == 352.9


def test_the_steady_head_offset_is_stored_and_said_by_info(run_file, tmp_path, capsys):
    """ModelFit.steady_head_offset_m (velab.fitting.offset) round-trips, and `velab info` says the best
    model's; a fit stored before it has none (0: the baseline's mean was the steady head) and no line."""
    p = tmp_path / "a.h5"
    shutil.copy(run_file, p)
    r = _result()
    r.models[1].steady_head_offset_m = -6.64e-4
    save_fit(p, r, "new")
    old = _result().to_dict()
    for m in old["models"]:
        del m["steady_head_offset"]
    save_fit(p, old, "old")
    with open_run_file(p) as fh:
        assert read_fit_group(fh["entry/fits/new"])["S1"].steady_head_offset_m == -6.64e-4
        assert read_fit_group(fh["entry/fits/old"])["S1"].steady_head_offset_m == 0.0
    capsys.readouterr()
    assert main(["info", str(p)]) == 0
    lines = [x for x in capsys.readouterr().out.splitlines() if "steady head:" in x]
    assert lines == ["    steady head: S1 fits the baseline's mean -0.664 mm off (every model fits this offset, "
                     "the baseline its prior)"]


def test_a_model_error_element_is_stored_and_found_again_in_an_older_group(run_file, tmp_path):
    """ModelFit.model_error_elements (velab.fitting.selection.mark_model_errors) round-trips through the fit
    group; a group stored before the field existed (support "model error", no field) reads back with the same
    elements, found by the same rule on the fit's stored tau box, and the same note."""
    p = tmp_path / "a.h5"
    shutil.copy(run_file, p)
    lo, hi = 0.0137, 10.0
    el = ModelFit("EL", 0, 1, False, 1000, math.exp(-9.99e-3), 420.0, (), (), 0.0)
    # an element on the lower tau bound holding 5e-5 of the compliance: a model error (E = 2e13 Pa: J' = 5e-5)
    s1 = ModelFit("S1", 1, 3, False, 1000, math.exp(-10e-3), 420.0, (2e13,), (2e13 * 0.016,), 0.0, J_rel=(5e-5,))
    apply_criteria([el, s1], "white", (lo, hi))
    assert s1.model_error_elements == (0,) and s1.support == "model error"
    r = SweepResult(n=1000, window_s=1.0, sample_rate_hz=1000.0, method="auto", models=[el, s1], selection="white",
                    settings={"models": [0, 1], "bounds": {"tau_min_s": lo, "tau_max_s": hi}})
    old = r.to_dict()
    assert old["models"][1]["model_error_elements"] == [0] and old["models"][0]["model_error_elements"] == []
    for m in old["models"]:
        del m["model_error_elements"]
    save_fit(p, r, "new")
    save_fit(p, old, "old")
    with open_run_file(p) as fh:
        for name in ("new", "old"):
            back = read_fit_group(fh[f"entry/fits/{name}"])
            assert back["S1"].model_error_elements == (0,) and back["EL"].model_error_elements == (), name
            assert back["S1"].note == "S1 = EL + a model-error element" and back["S1"].support == "model error"


def test_missing_fields_take_defaults(run_file, tmp_path):
    p = tmp_path / "a.h5"
    shutil.copy(run_file, p)
    d = {"method": "auto", "window": 1.0, "n": 10, "models": [{"name": "S1", "m": 1, "k": 3, "elements": []}]}
    save_fit(p, d, "sparse")
    with open_run_file(p) as fh:
        sweep = read_fit_group(fh["entry/fits/sparse"])
    assert sweep.models[0].name == "S1" and math.isnan(sweep.models[0].F)


def test_format_1_0_fit_groups_are_read(run_file, tmp_path, capsys):
    """velab 0.1's groups: everything in attributes, elements as E_pa/eta_pa_s datasets."""
    p = tmp_path / "old.h5"
    shutil.copy(run_file, p)
    with h5py.File(p, "r+") as fh:
        g = fh["entry/fits"].create_group("auto_w1s")
        g.attrs.update({"NX_class": "NXprocess", "method": "auto", "window_s": 1.0, "n": 1000, "best_model": "S1",
                        "settings": json.dumps({"models": [1]}), "sample_rate_hz": 1000.0, "date": "2026-01-01"})
        s = g.create_group("S1")
        s.attrs.update({"m": 1, "k": 3, "F": 0.01, "aic": -5.0, "aicc": -4.9, "bic": -3.0, "delta_aic": 0.0,
                        "weight": 1.0, "wave_speed_m_s": 352.0, "lag1_autocorr": 0.2, "support": "substantial",
                        "reduced": False})
        s["E_pa"], s["eta_pa_s"] = np.array([8e9]), np.array([4e9])
    with open_run_file(p) as fh:
        sweep = read_fit_group(fh["entry/fits/auto_w1s"])
    assert sweep.best.name == "S1" and sweep["S1"].tau_s == (0.5,) and sweep["S1"].wave_speed_m_s == 352.0
    assert main(["info", str(p)]) == 0
    assert "fit auto_w1s: method auto" in capsys.readouterr().out
    assert read_run(p).fit_names == ["auto_w1s"]
