"""One fit path (velab.fitting.prepare): the recorder's online fit and ``velab fit`` of the run file
agree exactly, at 1 kHz and 10 kHz; the fit's record says its rate and filter; decimation keeps
the calibration (same best model and wave speed at 1 and 10 kHz on one synthetic record)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from record_helpers import rate_clock
from velab.commands.fit import fit_file
from velab.config import load_material, load_rig
from velab.errors import DataError
from velab.fitting import fit_record, prepare_record
from velab.fitting.prepare import decimate_head, fit_decimation
from velab.fitting.window import BASELINE_S
from velab.recording import Recorder, RecordSettings
from velab.recording.timeline import PRE_TRIGGER_KEPT_S
from velab.fitting.results import SweepResult
from velab.model import valve_head
from velab.runfiles.summary import read_fits

WINDOW_S = 4.0
MODELS = (0, 1, 2)


@pytest.mark.parametrize("sim_config, rate", [("dataq", 1000.0), ("dataq", 10000.0), ("labjack", 1000.0),
                                              ("default", 10000.0)])
def test_online_fit_is_reproduced_by_velab_fit(tmp_path, sim_config, rate):
    """On the products' benches (the DATAQ DI-2108, the LabJack T7: a fired valve, its stroke measured) and velab's
    own (the SADC-4 streaming ADC, the servo actuator)."""
    # --duration equal to the fit window: the run must get its fit (the window closes on the boundary)
    s = RecordSettings(duration_s=WINDOW_S, fit_window_s=WINDOW_S, pretrigger_s=1.5, sample_rate_hz=rate,
                       fit_models=MODELS, out_dir=tmp_path)
    with Recorder.simulated(s, sim_config, material="A", clock=rate_clock(rate)) as rec:
        summary = rec.run()
    assert summary.status == "completed", summary.reason
    assert summary.fit is not None, summary.fit_error
    online = SweepResult.from_dict(read_fits(summary.path)["online"])
    assert online.record_rate_hz == rate
    q = 10 if rate == 10000.0 else 1
    assert online.sample_rate_hz == rate / q and online.settings["record"]["decimation"] == q
    assert ("FIR" in online.anti_alias_filter) == (q > 1)
    offline, _ = fit_file(str(summary.path), {
        "models": list(MODELS), "window_s": WINDOW_S, "method": "auto", "reduced": False, "starts": None,
        "polish": True, "save": False, "name": None, "plot": None, "tau_min_s": None, "tau_max_s": None,
        "selection": "ar1", "friction": None, "friction_unsteady": None})
    assert offline.best.name == online.best.name
    assert offline.settings["record"] == online.settings["record"]
    for a, b in zip(online.models, offline.models):
        assert a.name == b.name
        assert a.F == b.F and a.wave_speed_m_s == b.wave_speed_m_s  # exactly: the same data, the same fit
        assert np.array_equal(a.tau_s, b.tau_s) and np.array_equal(a.E_pa, b.E_pa)


def test_recorder_keeps_what_the_steady_head_needs():
    assert PRE_TRIGGER_KEPT_S >= BASELINE_S + 1.0


def test_prepare_record_window_steady_head_and_errors():
    rig = load_rig("perugia")
    fs = 1000.0
    t = np.arange(-5000, 5000) / fs + 0.25  # trigger at 0.25 s on the run's axis
    head = np.full(t.size, 30.0)
    head[t >= 0.25] += np.sin(np.arange((t >= 0.25).sum()) / 50.0)
    head[t < 0.25 - BASELINE_S - 0.5e-3] = 1e6  # before the baseline: not used
    head[:3750] = -1e6  # before a break in the baseline (t = -1 s): not used either
    head[3750] = np.nan
    rec = prepare_record(t, head, 0.25, rig, 3.0, record_rate_hz=fs)
    assert rec.steady_head_m == 30.0 and rec.decimation == 1 and rec.h.size == 3000
    assert rec.t[0] == pytest.approx(0.0, abs=1e-12) and rec.h[0] == 0.0
    with pytest.raises(DataError, match="longer than the record"):
        prepare_record(t, head, 0.25, rig, 6.0, record_rate_hz=fs)
    bad = head.copy()
    bad[6000] = np.nan  # 1 s after the trigger
    with pytest.raises(DataError, match="NaN"):
        prepare_record(t, bad, 0.25, rig, 3.0, record_rate_hz=fs)
    gap = np.delete(np.arange(t.size), 5500)
    with pytest.raises(DataError, match="not uniform"):
        prepare_record(t[gap], head[gap], 0.25, rig, 3.0, record_rate_hz=fs)


def test_decimation_rate_and_filter():
    rig = load_rig("perugia")
    assert fit_decimation(rig, 1000.0) == 1 and fit_decimation(rig, 10000.0) == 10
    assert fit_decimation(rig, 50000.0) == 50
    # the filter passes the manoeuvre's band untouched and takes out what would alias
    fs, q = 10000.0, 10
    n = 20000
    tt = np.arange(n) / fs
    slow = np.sin(2 * math.pi * 20.0 * tt)
    fast = np.sin(2 * math.pi * 1234.0 * tt)
    d = decimate_head(slow + fast, q)
    mid = slice(50, d.size - 50)
    assert np.max(np.abs(d[mid] - slow[::q][mid])) < 2e-3


def test_same_calibration_at_1_and_10_kHz():
    """Issue 13: same best model and wave speed (within 0.3 m/s) at 1 and 10 kHz; the 10 kHz record is
    fitted at 1 kHz (decimated), the rate and filter are in the result."""
    rig = load_rig("perugia").with_changes(friction="linear")
    mat = load_material("A")
    rng = np.random.default_rng(13)
    out = {}
    for fs in (1000.0, 10000.0):
        t = np.arange(-int(fs), int(20 * fs)) / fs
        head = rig.steady_head_m + valve_head(t, rig, mat) + rng.normal(0, 0.1, t.size)
        r = fit_record(t, head, 0.0, rig, 20.0, record_rate_hz=fs, models=range(5))
        out[fs] = r
    lo, hi = out[1000.0], out[10000.0]
    assert hi.sample_rate_hz == 1000.0 and hi.record_rate_hz == 10000.0 and "FIR" in hi.anti_alias_filter
    assert lo.best.name == hi.best.name == "S3"
    assert abs(lo.best.wave_speed_m_s - hi.best.wave_speed_m_s) < 0.3
    assert abs(hi.best.wave_speed_m_s - 353.73) < 0.3
