"""Column separation (issue 24, part 4): the vapour-pressure head, the interlock's downsurge, `velab synth`'s
refusal, and a record that cavitated.

The reference rig with a 4 m reservoir: steady head 3.7 m at the transducer, Joukowsky head 17.8 m,
so the first downsurge would reach -14 m where the water boils at -10.1 m (20 C).
"""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import numpy as np
import pytest

from record_helpers import cli
from velab.cavitation import (DETECTION_MARGIN_M, cavitating, predict_downsurge, rig_vapour_head_m,
                              vapour_head_m, vapour_pressure_pa)
from velab.cli import main
from velab.config import load_rig
from velab.errors import ConfigError
from velab.recording import Recorder, RecordSettings, RunRefused
from velab.recording.safety import predict_surge
from velab.rig import rig_from_dict

ROOT = Path(__file__).resolve().parents[1]


def _rig_file(tmp_path, reservoir_m=4.0, temperature_c=None, law="imposed", name="low"):
    text = (ROOT / "configs/rigs/perugia.toml").read_text()
    text = re.sub(r"(?m)^reservoir_head_m = [0-9.]+", f"reservoir_head_m = {reservoir_m!r}", text)
    text = re.sub(r'(?m)^law = "orifice"', f'law = "{law}"', text)
    if temperature_c is not None:
        text = text.replace("[fluid]\n", f"[fluid]\ntemperature_c = {temperature_c!r}\n")
    path = tmp_path / f"{name}.toml"
    path.write_text(text)
    return path


def test_vapour_pressure_of_water():
    # IAPWS-IF97 saturation line: 611.2 Pa at the triple point, 2339 Pa at 20 C, 101.42 kPa at 100 C
    assert vapour_pressure_pa(0.01) == pytest.approx(611.66, rel=2e-3)
    assert vapour_pressure_pa(20.0) == pytest.approx(2339.2, abs=1.0)
    assert vapour_pressure_pa(100.0) == pytest.approx(101_418, rel=1e-3)
    assert vapour_head_m(20.0, 998.2) == pytest.approx((2339.2 - 101_325) / (998.2 * 9.81), abs=1e-3)
    assert -10.2 < vapour_head_m() < -10.0  # physics.md 11: about -10.1 m at sea level
    # 19.95 kPa at 60 C: the water boils 1.8 m of head sooner
    assert vapour_head_m(60.0) - vapour_head_m(20.0) == pytest.approx((19_946 - 2339.2) / (998.2 * 9.81), abs=0.01)
    with pytest.raises(ValueError):
        vapour_pressure_pa(-5.0)


def test_rig_file_temperature(tmp_path):
    warm = load_rig(_rig_file(tmp_path, 35.0, temperature_c=60.0))
    assert warm.fluid.temperature_c == 60.0
    assert rig_vapour_head_m(warm) == pytest.approx(vapour_head_m(60.0, warm.fluid.density_kg_m3))
    assert load_rig("perugia").fluid.temperature_c == 20.0  # the default
    with pytest.raises(ConfigError, match=r"\[fluid\] temperature_c"):
        load_rig(_rig_file(tmp_path, 35.0, temperature_c=150.0, name="hot"))
    # a rig stored in a run file before the key existed reads as 20 C
    d = load_rig("perugia").to_dict()
    del d["fluid"]["temperature_c"]
    assert rig_from_dict(d).fluid.temperature_c == 20.0


def test_predicted_downsurge(tmp_path):
    ref = load_rig("perugia")
    ok = predict_downsurge(ref)
    assert ok.allowed and ok.min_head_m == pytest.approx(ref.steady_head_m - 1.1 * ref.joukowsky_head_m())
    low = load_rig(_rig_file(tmp_path))
    bad = predict_downsurge(low)
    assert not bad.allowed and bad.min_head_m < bad.vapour_head_m
    assert "cavitation" in bad.message and "vapour-pressure head -10.11 m (2.34 kPa at 20 C)" in bad.message
    # the interlock: refused on the rig's own numbers, and on a measured steady head that is too low
    s = RecordSettings(out_dir=tmp_path)
    pred = predict_surge(low, s)
    assert not pred.allowed and pred.cavitation and pred.message == predict_surge(low, s).message
    assert "cavitation" in pred.message and "\n" not in pred.message
    assert predict_surge(ref, s).allowed and not predict_surge(ref, s).cavitation
    assert not predict_surge(ref, s, steady_head_m=8.0).allowed  # the measured head decides too
    # a partial closure stops less flow: a shallower downsurge
    half = predict_surge(low.with_changes(reservoir_head_m=12.0), s.with_changes(end_position_pct=50.0))
    assert half.allowed and half.min_head_m > predict_surge(low.with_changes(reservoir_head_m=12.0), s).min_head_m


def _sim_config(tmp_path, rig_path):
    text = (ROOT / "configs/sim/default.toml").read_text()
    text = re.sub(r'(?m)^rig = "perugia"', f'rig = "{rig_path}"', text)
    path = tmp_path / "sim_low.toml"
    path.write_text(text)
    return path


def test_interlock_refuses_a_manoeuvre_that_would_cavitate(tmp_path):
    """The real recorder on the simulated bench whose reservoir is 4 m: refused before anything moves."""
    rig_path = _rig_file(tmp_path, law="orifice")
    out = tmp_path / "runs"
    out.mkdir()
    s = RecordSettings(duration_s=3, fit=False, out_dir=out)
    with Recorder.simulated(s, str(_sim_config(tmp_path, rig_path)), clock="fast", rig=load_rig(rig_path)) as rec:
        with pytest.raises(RunRefused, match="cavitation") as err:
            rec.run()
        assert "vapour-pressure head" in str(err.value) and err.value.exit_code == 3
        assert rec.sim.rig.trigger_count == 0 and rec.sim.rig.state().name == "IDLE"
    assert list(out.iterdir()) == []


def test_velab_record_refuses_with_exit_3(tmp_path):
    rig_path = _rig_file(tmp_path, law="orifice")
    p = cli(["record", "--simulate", "--fast", "--sim-config", str(_sim_config(tmp_path, rig_path)), "--rig",
             str(rig_path), "--duration", "3", "--no-fit", "--out-dir", str(tmp_path)])
    assert p.returncode == 3, p.stderr
    lines = [line for line in p.stderr.splitlines() if "cavitation" in line]
    assert len(lines) == 1 and "vapour-pressure head" in lines[0] and "Traceback" not in p.stderr


def test_velab_synth_refuses_a_rig_that_would_cavitate(tmp_path, capsys):
    out = tmp_path / "low.h5"
    assert main(["synth", "--rig", str(_rig_file(tmp_path)), "--duration", "2", "-o", str(out)]) == 3
    err = capsys.readouterr().err
    assert "cavitation" in err and "vapour-pressure head" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_a_record_clipped_at_the_vapour_head_gets_the_cavitation_warning(tmp_path, capsys):
    """A record of the 35 m rig lowered to the 4 m reservoir's heads and clipped where the water boils, as
    a transducer sees column separation: imported with the 4 m rig, the fit warns that its model does not
    hold there."""
    src = tmp_path / "a.h5"
    assert main(["synth", "--rig", str(_rig_file(tmp_path, 35.0, name="ref")), "--material", "A", "--friction",
                 "linear", "--duration", "4", "-o", str(src)]) == 0
    from velab.runfiles import read_run

    run = read_run(src)
    low = load_rig(_rig_file(tmp_path))
    hv = rig_vapour_head_m(low)
    head = np.maximum(run.head_m - (run.rig.steady_head_m - low.steady_head_m), hv)
    assert (head == hv).sum() > 50  # the plateau of a cavity
    csv_path = tmp_path / "clipped.csv"
    with open(csv_path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", "head"])
        w.writerows(zip((f"{x:.6f}" for x in run.time_s), (f"{x:.6f}" for x in head)))
    imported = tmp_path / "clipped.h5"
    assert main(["import", str(csv_path), "--rig", str(_rig_file(tmp_path)), "-o", str(imported)]) == 0
    capsys.readouterr()
    assert main(["fit", str(imported), "--window", "3", "--models", "0-1", "--json", "--no-save"]) == 0
    doc = json.loads(capsys.readouterr().out)
    cav = [w for w in doc["warnings"] if w["code"] == "cavitation"]
    assert len(cav) == 1 and "does not hold there" in cav[0]["message"]
    assert doc["adequacy"]["min_head_m"] == pytest.approx(hv, abs=0.05)
    assert doc["adequacy"]["vapour_head_m"] == pytest.approx(hv)
    # the same record not clipped, on the reference rig's heads: no cavitation warning
    capsys.readouterr()
    assert main(["fit", str(src), "--window", "3", "--models", "0-1", "--json", "--no-save"]) == 0
    assert "cavitation" not in [w["code"] for w in json.loads(capsys.readouterr().out)["warnings"]]


def test_detection_margin():
    t = np.arange(6) * 0.1
    hv = -10.1
    assert cavitating(t, [5.0, 0.0, -9.0, -9.5, 3.0, 4.0], hv) is None
    f = cavitating(t, [5.0, hv + DETECTION_MARGIN_M - 0.01, hv, np.nan, 3.0, hv], hv)
    assert f.samples == 3 and f.first_s == pytest.approx(0.1) and f.last_s == pytest.approx(0.5)
    assert f.min_head_m == hv and "does not hold there" in f.message()
