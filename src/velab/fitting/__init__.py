"""Calibration of the Sm pipe-wall models and model selection by AIC.

Public API (pure computation, no Qt, no I/O, thread-safe)::

    from velab.fitting import fit_sweep
    result = fit_sweep(t, h, rig, models=range(7), window_s=20, method="auto",
                       reduced=False, progress=None, initial=None)
    result.best, result.report(), result.to_dict(), result["S3"].tau_s

One fit path for recorded runs (velab fit, the recorder's online fit, the GUI re-fit)::

    from velab.fitting import fit_record, prepare_record
    result = fit_record(t, head, trigger_time_s, rig, 20.0, record_rate_hz=fs)  # window, steady head, decimation

See docs/fitting.md for the method, the JSON schema and the fit-group layout.
"""

from velab.fitting.results import SELECTIONS, ModelFit, SweepResult, support_category
from velab.fitting.sweep import METHODS, fit_sweep, parse_models
from velab.fitting.prepare import PreparedRecord, fit_record, fit_run, prepare_record

__all__ = ["fit_sweep", "ModelFit", "SweepResult", "METHODS", "SELECTIONS", "parse_models", "support_category",
           "PreparedRecord", "prepare_record", "fit_record", "fit_run"]
