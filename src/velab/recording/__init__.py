"""The recording engine, one module per job (docs/recording.md, "Architecture").

settings    RecordSettings (validated; stored whole in the run file)
phases      the phase model, allowed commands per phase, end statuses and exit codes
types       events, faults, device statuses, run summaries, errors, the stages' Hooks
safety      surge interlock, pressure ceiling, output directory, sensor plausibility
devices     roles, connection, identities, profile contents, readiness checks
pressure    the pressure stage: a pressure source (velab.drivers.pressure_source) on its thread
trigger     the manoeuvre's trigger and the valve's safe state, outcomes named
timeline    time axis, gaps, baseline, trigger measurement, fit window
slow        the valve actuator's status and the flowmeter, polled
writer      the SWMR writer stage (gaps, events, quality, storage checks)
online_fit  the thin call into the fitter, scheduled as the window fills
layout      the run file's channels and its self-describing snapshot
run, engine the thin engine: sequencing, threads, phases (Recorder)
"""

from velab.recording.engine import Recorder
from velab.recording.phases import ACTIVE_PHASES, END_PHASES, PHASES, allowed_commands
from velab.recording.safety import SurgePrediction, ceiling_head, predict_surge
from velab.recording.settings import RecordSettings
from velab.recording.timeline import trigger_from_position
from velab.recording.types import DeviceFailure, DeviceStatus, Fault, RecorderEvent, RunRefused, RunSummary

__all__ = ["ACTIVE_PHASES", "END_PHASES", "PHASES", "DeviceFailure", "DeviceStatus", "Fault", "RecordSettings",
           "Recorder", "RecorderEvent", "RunRefused", "RunSummary", "SurgePrediction", "allowed_commands",
           "ceiling_head", "predict_surge", "trigger_from_position"]
