"""FitOptions (what a user chooses, checked at the door) and FitSettings (the result's typed settings, the JSON
unchanged)."""

from __future__ import annotations

import json
import pickle

import pytest

from velab.errors import DataError
from velab.fitting.options import FitOptions
from velab.fitting.results import SweepResult
from velab.fitting.settings import UNSET, FitSettings


def test_options_are_checked_when_made_each_in_one_line_naming_it():
    cases = [
        (dict(method="newton"), "unknown fit method 'newton'"),
        (dict(selection="bic"), "unknown model selection 'bic'"),
        (dict(manoeuvre="sigmoid"), "unknown manoeuvre input 'sigmoid'"),
        (dict(friction="laminar"), "unknown friction law 'laminar'"),
        (dict(friction_unsteady="zielke"), "unknown unsteady friction law 'zielke'"),
        (dict(models="0-9"), "bad model list"),
        (dict(models=[]), "bad model list"),
        (dict(starts=0), "starts must be a whole number of at least 1"),
        (dict(starts=True), "starts must be a whole number"),
        (dict(threads=3), "threads must be 1 or 2"),
        (dict(window_s=-1.0), "the fit window must be a positive number"),
        (dict(window_s=float("nan")), "the fit window must be a positive number"),
        (dict(tau_min_s=2.0, tau_max_s=1.0), "tau_min_s 2 s must be below tau_max_s 1 s"),
        (dict(tau_min_s="soon"), "tau_min_s must be a number of seconds"),
    ]
    for choices, message in cases:
        with pytest.raises(DataError, match=message) as err:
            FitOptions(**choices)
        assert "\n" not in str(err.value), choices
    with pytest.raises(DataError, match="unknown fit option colour"):
        FitOptions.of(colour="blue")


def test_options_normalise_and_change_by_name():
    o = FitOptions(models="S3,EL,1", window_s=8)
    assert o.models == (0, 1, 3) and o.window_s == 8.0 and o.default_search
    assert FitOptions(models=range(2)).models == (0, 1)
    p = o.replace(method="nelder-mead")
    assert p.method == "nelder-mead" and o.method == "auto" and not p.default_search
    assert FitOptions.of(None, polish=False) == FitOptions(polish=False)
    with pytest.raises(Exception):
        o.method = "evolution"  # frozen
    # what a fit was made with: every choice but the threads (which do not change the result)
    assert o.key() == o.replace(threads=1).key() != o.replace(seed=1).key()


def test_settings_are_typed_frozen_and_their_json_is_the_dict_they_were_made_from():
    doc = {"models": [0, 1], "lead": None, "bounds": {"tau_min_s": 0.01}, "manoeuvre": {"source": "fitted"},
           "a_newer_key": {"x": 1}}
    s = FitSettings.from_dict(doc)
    assert s.models == [0, 1] and s.lead is None and s.manoeuvre == {"source": "fitted"} and s.record is UNSET
    assert s.to_dict() == doc and json.loads(json.dumps(s.to_dict())) == doc
    # the JSON's mapping view: a key never set is absent, as in the dict
    assert s["lead"] is None and "lead" in s and "record" not in s and s.get("record") is None
    with pytest.raises(KeyError):
        s["record"]
    assert s["a_newer_key"] == {"x": 1}
    t = s.replace(record={"decimation": 1})
    assert t.record == {"decimation": 1} and s.record is UNSET  # a new one; the old unchanged
    with pytest.raises(TypeError, match="no field colour"):
        s.replace(colour=1)
    with pytest.raises(Exception):
        s.models = [3]
    assert pickle.loads(pickle.dumps(t)) == t and pickle.loads(pickle.dumps(UNSET)) is UNSET


def test_a_result_reads_and_writes_its_settings_as_they_were():
    doc = {"n": 10, "window": 1.0, "sample_rate_hz": 10.0, "method": "auto", "selection": "ar1",
           "settings": {"models": [0], "selection": "ar1", "friction": {"steady": "linear"}, "future": 2},
           "models": []}
    r = SweepResult.from_dict(doc)
    assert isinstance(r.settings, FitSettings) and r.settings.friction == {"steady": "linear"}
    # a dict given is read as FitSettings, at construction and on assignment
    r.settings = {"models": [1]}
    assert isinstance(r.settings, FitSettings) and r.settings.models == [1]
    assert SweepResult.from_dict(doc).settings.to_dict() == doc["settings"]
