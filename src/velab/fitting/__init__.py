"""Calibration of the Sm pipe-wall models and model selection by AIC.

Public API (pure computation, no Qt, no I/O, thread-safe)::

    from velab.fitting import fit_sweep
    result = fit_sweep(t, h, rig, models=range(7), window_s=20, method="auto",
                       reduced=False, progress=None, initial=None)
    result.best, format_report(result), result.to_dict(), result["S3"].tau_s

One fit path for recorded runs (velab fit, the recorder's online fit, the GUI re-fit)::

    from velab.fitting import fit_record, prepare_record
    result = fit_record(t, head, trigger_time_s, rig, 20.0, record_rate_hz=fs)  # window, steady head, decimation

See docs/fitting.md for the method, the JSON schema and the fit-group layout.
"""

from __future__ import annotations

from velab.lazy import lazy_exports

# the public names and their modules, imported on first use (PEP 562): the recorder and the GUI read the
# options (velab.fitting.options) without loading scipy, which only the fit itself needs
_EXPORTS = {
    "SELECTIONS": "selection", "ModelFit": "results", "SweepResult": "results", "support_category": "selection",
    "format_report": "report",
    "METHODS": "options", "FitOptions": "options", "parse_models": "options",
    "fit_sweep": "sweep", "SweepContext": "sweep",
    "PreparedRecord": "prepare", "prepare_record": "prepare", "fit_record": "entry",
    "fit_run": "entry",
}
__all__ = list(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, globals(), _EXPORTS)
