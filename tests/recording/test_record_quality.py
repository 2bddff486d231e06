"""One sensor-quality path, for both pressure sources (streaming ADC, buffered Modbus ADC).

The faults come from a sim config's ``[[faults.schedule]]`` (the config path, through the API):
a stuck transducer, a 2 mA (open loop) and a 22 mA (NE43 failure-high) loop current, a NaN burst,
an implausible reply (corrupted stream frames: dropped, a counted gap; Modbus-RTU replies with a
bad CRC: refused and re-read, the module's ring keeps the samples; when it never stops, a failed
run naming the ADC).
Each is flagged by the driver's per-sample quality (the one source), written into the file's
``pressure_quality`` channel, detected once (one fault event per quality code), and ends the run
as docs/recording.md says: before the trigger a sensor fault aborts the run (blind: no manoeuvre),
after it the data are flagged and the run completes with faults; a 22 mA reading is a sensor
fault, never a pressure-ceiling abort. Faults after the trigger have a duration: they clear
again mid-record, and the samples after them are OK again.
"""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest

from record_helpers import ABORTED, CWF, FAILED, MODBUS_ADC_CLOCK, fast_sim, recorder, run_bounded, short_settings, thread_errors  # noqa: F401
from velab.drivers.blocks import QUALITY_CODES
from velab.runfiles.reader import read_run
from velab.simulators.bench import load_sim_config

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]  # the integration layer: the simulated bench (tests/recording: the stages alone)

SENSOR = {  # fault -> (schedule entry, expected quality by source)
    "stuck": ({"device": "rig", "fault": {"stuck_channels": [0]}}, {"streaming_adc": "stale", "pressure_adc": "stale"}),
    "2mA": ({"device": "rig", "fault": {"channel_mA": {"0": 2.0}}},
            {"streaming_adc": "open_loop", "pressure_adc": "open_loop"}),
    "22mA": ({"device": "rig", "fault": {"channel_mA": {"0": 22.0}}},
             {"streaming_adc": "sensor_fault", "pressure_adc": "sensor_fault"}),
    # the Modbus ADC's ring has no invalid-conversion code: a NaN input reads 0 mA, an open loop
    "nan": ({"device": "rig", "fault": {"channel_mA": {"0": math.nan}}},
            {"streaming_adc": "nan", "pressure_adc": "open_loop"}),
}
IMPLAUSIBLE = {"streaming_adc": {"device": "streaming_adc", "fault": {"corrupt_every": 3}},
               "pressure_adc": {"device": "pressure_adc", "fault": {"corrupt_crc": True}}}
# The Modbus ADC's corrupted replies are tested over RTU (its CRC catches every one). Over Modbus TCP
# a flipped byte has no checksum to fail: which outcome it has depends on which counter value it hits
# (docs/recording.md, "Modbus TCP corruption"), so it is no deterministic test.
IMPLAUSIBLE_ENDPOINTS = {"pressure_adc": [{"transport": "rtu-socket", "port": 0}]}
# after the trigger: this many corrupted replies (the client's retries: 3 attempts per request, so two polls refused)
POLLED_CORRUPT = 6
SCENARIOS = [(src, f, at) for src in ("streaming_adc", "pressure_adc") for f in (*SENSOR, "implausible")
             for at in ("arm", "trigger")]


def sim_config(entry: dict, at: str, endpoints: dict | None = None) -> dict:
    _, doc = load_sim_config("default")
    doc = copy.deepcopy(dict(doc))
    # after the trigger a sensor fault lasts 0.4 s of device time. Corrupted Modbus replies (not samples: the ring
    # keeps those) are counted instead: the next POLLED_CORRUPT replies from 0.4 s after the trigger on, whenever the
    # recorder polls. A time window depends on the host: 0.4 s (33 ms of host time at the fast clock) fell between a
    # loaded host's polls and the run was clean; 2 s (0.17 s) left the ring (4 s) 0.17 s of host time to catch up,
    # which three loads at once did not (a 538-sample gap)
    polled = entry["fault"].get("corrupt_crc")
    if at == "arm":
        entry = dict(entry, at="arm+0.2")
    elif polled:
        # the window outlasts the record: the read that brings the record's last sample comes after 0.4 s, inside it
        # (a loaded pair's reader made no request within a 2.5 s window, 0.21 s of host time: "completed")
        entry = dict(entry, at="trigger+0.4", duration_s=60.0, fault=dict(entry["fault"], count=POLLED_CORRUPT))
    else:
        entry = dict(entry, at="trigger+0.4", duration_s=0.4)
    doc["faults"] = {"schedule": [entry]}
    if endpoints:
        doc["devices"] = copy.deepcopy(dict(doc["devices"]))
        for device, eps in endpoints.items():
            doc["devices"][device]["endpoints"] = eps
    return doc


@pytest.mark.parametrize("source,fault,at", SCENARIOS, ids=[f"{s}-{f}-at_{a}" for s, f, a in SCENARIOS])
def test_sensor_quality_path(tmp_path, thread_errors, source, fault, at):
    entry = IMPLAUSIBLE[source] if fault == "implausible" else SENSOR[fault][0]
    sim = fast_sim(sim_config(entry, at, IMPLAUSIBLE_ENDPOINTS if fault == "implausible" else None),
                   clock=MODBUS_ADC_CLOCK if source == "pressure_adc" else "fast")  # (every sample counts here)
    # at arm: a long baseline, so that the fault (0.2 s after ARM) is in it before the trigger goes out; 3 s after
    # the trigger (0.25 s of host time at the fast clock): on a loaded host the TRIGGER reaches the actuator up
    # to ~0.1 s of host time after the recorder's estimate, and a 1.5 s record could end before the stroke. The
    # baseline at arm: 3 s (a stuck channel is named after a run of equal samples; with 1 s, two suites at once
    # let the trigger go out first: 0.8 s of device time is 67 ms of host time)
    s = short_settings(tmp_path, duration_s=3.0, pretrigger_s=3.0 if at == "arm" else 0.5)
    faults: list = []
    out = run_bounded(recorder(sim, s, source=source), faults)
    assert not thread_errors, thread_errors
    assert out.error is None, out.error
    summary = out.summary
    run = read_run(summary.path)
    assert not run.incomplete and run.status == summary.status
    codes = run.channels["pressure_quality"]
    seen = {QUALITY_CODES[int(c)].value for c in np.unique(codes)}
    pressure_faults = [f for f in faults if f["role"] == "pressure"]
    assert all(f["device"] == source for f in pressure_faults), pressure_faults
    print(f"{source} {fault} at {at}: {summary.status} in {out.elapsed_s:.1f} s; codes {sorted(seen)}, "
          f"gaps {run.gaps}; {summary.reason[:100]}")
    if fault == "implausible":  # never taken as data: dropped (a counted gap), or the device named and the run marked
        assert pressure_faults
        if source == "pressure_adc" and at == "arm":  # corrupted for good: no trustworthy sample -> failed, named
            assert summary.status == FAILED and summary.reason.startswith("pressure_adc (pressure source)")
            return
        assert summary.status == CWF, (summary.status, summary.reason)
        if source == "pressure_adc":  # every bad-CRC reply refused and re-read: the module's ring kept the samples
            assert not run.gaps and np.all(np.diff(run.channels["sample_index"]) == 1), run.gaps
        else:
            assert run.gaps, seen  # the corrupted frames dropped: a counted gap in the file
        return
    want = SENSOR[fault][1][source]
    assert want in seen, (want, seen)
    assert seen <= {"ok", want}, seen  # nothing else flagged: one path, one code
    detected = [f for f in pressure_faults if f["kind"] in ("quality", "stuck")]
    assert len(detected) == 1 and detected[0]["quality"] == want, [str(f) for f in detected]  # detected once
    assert any(k == "fault" and want in m for _, k, m in run.events), run.events  # in the file's event log
    assert "pressure ceiling" not in summary.reason  # a sensor fault, never an overpressure
    if at == "arm":  # blind before the trigger: no manoeuvre, the armed valve cancelled
        assert summary.status == ABORTED and "before the trigger" in summary.reason, summary.reason
        assert out.triggers == 0 and out.valve_state in ("ABORTED", "IDLE")
    else:  # flagged data after the trigger: completed with faults; the fault cleared, later samples are OK
        assert summary.status == CWF, (summary.status, summary.reason)
        assert out.triggers == 1
        flagged = np.flatnonzero(codes != 0)
        assert flagged.size and codes[-1] == 0 and flagged[-1] < codes.size - 1
        t = run.time_s
        assert 0.3 < t[flagged[0]] - run.trigger_time_s < 0.9, t[flagged[0]] - run.trigger_time_s
