"""Several measurement sections recorded end to end on the simulated bench (real sockets, fast clock): the
reference rig with a second transducer at 40 % of the length (configs/rigs/perugia_two_sections.toml),
wired to input 2 of both pressure ADCs (configs/sim/two_sections.toml). The run file has a head per
transducer, named as in the rig, with its position; the online fit and ``velab fit`` of the file fit both
sections and agree exactly; a fault on one transducer's channel flags the run; a bench that cannot record
the rig's transducers is one line and records nothing."""

from __future__ import annotations

import json
import tomllib

import h5py
import numpy as np
import pytest

from record_helpers import CWF, MODBUS_ADC_CLOCK, fast_sim, recorder, run_bounded, thread_errors  # noqa: F401 - a fixture
from velab.cli import main
from velab.commands.fit import fit_file
from velab.configpath import find_config
from velab.errors import ConfigError
from velab.fitting.sections import SectionsResult
from velab.recording import RecordSettings, RunRefused
from velab.runfiles.reader import read_run
from velab.runfiles.summary import read_fits
from velab.fitting.report import format_report

pytestmark = pytest.mark.slow  # the integration layer: the simulated bench (tests/recording: the stages alone)

WINDOW_S = 6.0
# S1..S3: material A's S3 named against the models below it. (S4 as well: the sections' AIC names S4 on
# some recordings -- 4 of 43 on the simulated bench, three with a section's F/noise at 1.07-1.10 --,
# which is the fitter's adequacy, not the recording's; docs/recording.md "Several sections".)
MODELS = (1, 2, 3)
MID_X = 41.032
CLOCK = {"streaming_adc": "fast", "pressure_adc": MODBUS_ADC_CLOCK}  # (record_helpers: why not 12 x)
A_TRUE = 353.73


def two_sections(**recorder_table) -> dict:
    """The two-section sim config, its [recorder] table changed (e.g. pressure_source = "pressure_adc")."""
    doc = tomllib.loads(find_config("sim", "two_sections").read_text())
    doc["recorder"] = doc.get("recorder", {}) | recorder_table
    return doc


def settings(tmp_path, **kw) -> RecordSettings:
    base = dict(duration_s=WINDOW_S, fit_window_s=WINDOW_S, pretrigger_s=2.0, fit_models=MODELS, out_dir=tmp_path)
    return RecordSettings(**(base | kw))


def offline_fit(path) -> SectionsResult:
    result, _ = fit_file(str(path), {
        "models": list(MODELS), "window_s": WINDOW_S, "method": "auto", "reduced": False, "starts": None,
        "polish": True, "save": False, "name": None, "plot": None, "tau_min_s": None, "tau_max_s": None,
        "selection": "ar1", "friction": None, "friction_unsteady": None})
    return result


@pytest.mark.timeout(300)
@pytest.mark.parametrize("source", ["streaming_adc", "pressure_adc"])
def test_two_sections_recorded_and_fitted_online_as_velab_fit_does(tmp_path, source, thread_errors):  # noqa: F811
    rec = recorder(fast_sim(two_sections(), clock=CLOCK[source]), settings(tmp_path), source=source)  # (the map kept)
    out = run_bounded(rec, deadline_s=240.0)
    s = out.summary
    assert s is not None, out.error
    assert s.status == "completed" and s.exit_code == 0, s.reason
    assert not thread_errors

    # the file: a head per transducer, named as in the rig, with its position; each with its quality
    with h5py.File(s.path, "r") as fh:
        data = fh["entry/data"]
        assert {k: (data[k].attrs["transducer"], float(data[k].attrs["position_m"])) for k in ("head", "head_mid")} \
            == {"head": ("valve", 102.58), "head_mid": ("mid", MID_X)}
        assert "pressure_quality_mid" in fh["entry/instrument/pressure_transducer_mid"]
        bench = json.loads(fh["entry/instrument/bench_json"][()])
        assert bench["recorder"]["transducers"] == {"mid": "pressure_2"}
    run = read_run(s.path)
    assert [x.name for x in run.rig.sections] == ["valve", "mid"] and run.status == "completed"
    mid = run.channels["head_mid"]
    assert mid.shape == run.head_m.shape and not run.channels["pressure_quality_mid"].any()
    pre = run.time_s < run.trigger_time_s
    assert np.mean(mid[pre]) == pytest.approx(run.rig.steady_head_at_m(MID_X), abs=0.01)  # its own steady head
    first = lambda h: run.time_s[np.argmax(h - np.mean(h[pre]) > 1.0)]  # noqa: E731 - the front's arrival
    assert first(mid) - first(run.head_m) == pytest.approx((102.58 - MID_X) / A_TRUE, abs=0.005)

    # the online fit: every section, material A's S3, each section's noise ratio
    online = s.fit
    assert online.method == "sections" and s.best_model == "S3", format_report(online, elements=False)
    assert abs(online["S3"].wave_speed_m_s - A_TRUE) < 0.1 and online["S2"].delta_aic > 100
    assert [(x["name"], x["position_m"]) for x in online.sections] == [("valve", 102.58), ("mid", MID_X)]
    assert all(0.8 < x["noise_ratio"] < 1.25 and not x["disagrees"] for x in online.sections), online.sections
    assert read_fits(s.path)["online"]["sections"][1]["name"] == "mid"  # stored with the run

    # velab fit of the file: the same data, the same fit, exactly
    offline = offline_fit(s.path)
    assert offline.method == "sections" and offline.best.name == online.best.name
    for a, b in zip(online.models, offline.models):
        assert (a.name, a.F, a.wave_speed_m_s) == (b.name, b.F, b.wave_speed_m_s)
    assert [x["noise_ratio"] for x in offline.sections] == [x["noise_ratio"] for x in online.sections]


@pytest.mark.timeout(300)
def test_velab_record_simulate_two_sections_then_velab_fit(tmp_path, capsys):
    """The built-in example as an operator runs it: the two-section sim config, then velab fit of the file."""
    runs = tmp_path / "runs"
    code = main(["record", "--simulate", "--sim-config", "two_sections", "--fast", "--duration", "6", "--window", "6",
                 "--models", "1-3", "--out-dir", str(runs), "--json"])
    doc = json.loads(capsys.readouterr().out)
    assert code == 0 and doc["runs"][0]["status"] == "completed", doc
    run = doc["runs"][0]
    assert run["best_model"] == "S3" and [x["name"] for x in run["fit"]["sections"]] == ["valve", "mid"]
    assert main(["fit", run["path"], "--window", "6", "--models", "1-3", "--no-save", "--json"]) == 0
    fitted = json.loads(capsys.readouterr().out)
    assert fitted["method"] == "sections" and fitted["best"] == run["best_model"]
    assert [x["noise_ratio"] for x in fitted["sections"]] == [x["noise_ratio"] for x in run["fit"]["sections"]]


@pytest.mark.timeout(180)
def test_a_fault_on_the_mid_transducer_flags_the_run_and_shortens_every_sections_window(tmp_path, thread_errors):  # noqa: F811
    sim = fast_sim(two_sections())
    # a failure-high mid transducer (NE43: a sensor fault) 3 s after the trigger, for 0.3 s
    sim.schedule_fault("rig", at="trigger+3.0", duration_s=0.3, channel_mA={2: 22.0})
    faults = []
    out = run_bounded(recorder(sim, settings(tmp_path)), faults, deadline_s=150.0)
    s = out.summary
    assert s is not None, out.error
    assert s.status == CWF and s.exit_code == 6, s.reason  # never a plain "completed"
    (f,) = [f for f in faults if f["kind"] == "quality"]
    assert f["role"] == "pressure" and f["transducer"] == "mid" and f["channel"] == "pressure_2"
    assert f["quality"] == "sensor_fault" and "pressure ceiling" not in s.reason
    run = read_run(s.path)
    q_mid, q_valve = run.channels["pressure_quality_mid"], run.channels["pressure_quality"]
    flagged = run.time_s[q_mid == 7] - run.trigger_time_s
    assert flagged.size and 2.9 < flagged.min() and flagged.max() < 3.5 and not q_valve.any()
    # the fit: every section on the clean part of the window before the fault
    assert s.fit is not None and s.fit.method == "sections", s.fit_error
    assert 2.5 < s.fit.window_s < 3.1
    assert not thread_errors


@pytest.mark.timeout(120)
def test_a_mid_transducer_open_loop_before_arming_is_refused_naming_it(tmp_path):
    sim = fast_sim(two_sections())
    sim.set_fault("rig", channel_mA={2: 2.0})  # its loop broken: 2 mA
    out = run_bounded(recorder(sim, settings(tmp_path)))
    assert isinstance(out.error, RunRefused) and out.error.exit_code == 3
    assert "transducer mid (pressure_2) reading is open_loop" in str(out.error)
    assert out.triggers == 0 and not list(tmp_path.glob("*.h5"))  # nothing moved, nothing recorded


@pytest.mark.timeout(120)
def test_a_transducer_mapped_to_a_channel_that_is_not_a_pressure_is_one_line_and_records_nothing(tmp_path):
    sim = fast_sim(two_sections(transducers={"mid": "valve_position"}))
    out = run_bounded(recorder(sim, settings(tmp_path)))
    assert isinstance(out.error, ConfigError) and out.error.exit_code == 2
    msg = str(out.error)
    assert msg.startswith(sim.path) and "[recorder.transducers] mid: 'valve_position' is not a pressure channel" in msg
    assert out.triggers == 0 and not list(tmp_path.glob("*.h5"))


def test_a_rig_with_a_transducer_the_bench_does_not_map_is_refused_before_connecting(tmp_path, capsys):
    # the default simulated bench has no [recorder.transducers]: the two-section rig's "mid" has no channel
    code = main(["record", "--simulate", "--sim-config", "default", "--rig", "perugia_two_sections", "--fast",
                 "--out-dir", str(tmp_path)])
    err = capsys.readouterr().err
    assert code == 2 and "configs/sim/default.toml: [recorder.transducers]: no channel for the transducer 'mid'" in err
    assert "Traceback" not in err and not list(tmp_path.glob("*.h5"))
