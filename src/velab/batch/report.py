"""What a batch prints: the per-run table, one line per failure, the JSON document, the exit code."""

from __future__ import annotations

import math
import sys
from pathlib import Path

from velab.batch.runner import Batch
from velab.errors import ExitCode, one_line

_HEAD = (f"{'run':<32} {'status':<16}{'best':>5}{'a (m/s)':>10}{'F (m^2)':>13}{'F/noise':>9}{'2nd':>5}{'dAIC':>8}"
         f"{'time (s)':>9}  warnings")


def exit_code(batch: Batch) -> ExitCode:
    """The worst code of the runs (``ExitCode.worst``): 0 when every run was fitted."""
    return ExitCode.worst([o.get("exit_code", ExitCode.OK) if not o["ok"] else ExitCode.OK for o in batch.outcomes])


def _row(o: dict) -> str:
    name = Path(o["path"]).name
    name = name if len(name) <= 32 else name[:29] + "..."
    t = o.get("seconds")
    t = f"{t:>9.2f}" if isinstance(t, (int, float)) else f"{'-':>9}"  # no time: the fit never came back
    if not o["ok"]:
        return f"{name:<32} {'FAILED ' + o['reason']:<16}{'-':>5}{'-':>10}{'-':>13}{'-':>9}{'-':>5}{'-':>8}{t}"
    fit = o["fit"]
    models = fit.get("models") or []
    best = next((m for m in models if m.get("name") == fit.get("best")), {})
    others = sorted((m for m in models if m is not best), key=lambda m: _num(m.get("delta_aic")))
    second = others[0] if others else {}
    # the fit's own warnings (misfit, bound, cavitation: velab.fitting.adequacy), by code
    codes = sorted({str(w.get("code")) for w in fit.get("warnings") or [] if isinstance(w, dict)})
    return (f"{name:<32} {o['status']:<16}{fit.get('best', '-'):>5}{_num(best.get('wave_speed')):>10.2f}"
            f"{_num(best.get('F')):>13.5e}{_num(best.get('noise_ratio')):>9.2f}{second.get('name', '-'):>5}"
            f"{_num(second.get('delta_aic')):>8.2f}{t}  {','.join(codes) or '-'}")


def _num(v) -> float:
    return float(v) if isinstance(v, (int, float)) else math.nan


def table(batch: Batch) -> str:
    """One line per run (the best model, its wave speed, F and F / the record's noise, the runner-up and its
    delta AIC, the fit's warning codes), then a total."""
    lines = [_HEAD, *(_row(o) for o in batch.outcomes)]
    failed = sum(not o["ok"] for o in batch.outcomes)
    n = len(batch.outcomes)
    lines.append(f"{n} run{'s' if n != 1 else ''}: {n - failed} fitted, {failed} failed, "
                 f"{batch.seconds:.1f} s ({batch.where})")
    return "\n".join(lines)


def failure_lines(batch: Batch) -> list[str]:
    """``velab: FAILED PATH (reason): what went wrong``, one line per failed run."""
    return [f"velab: FAILED {one_line(o['path'])} ({o['reason']}): {one_line(o['error'])}"
            for o in batch.outcomes if not o["ok"]]


def json_doc(batch: Batch) -> dict:
    """``{runs: [...], batch: {...}}``: a fitted run is the single-run document (the fit's ``to_dict()``
    plus ``path`` and ``fit_name``) with its ``status`` and ``seconds``; a failed run is
    ``{path, status: "failed", reason, error, exit_code}``."""
    runs = []
    for o in batch.outcomes:
        if o["ok"]:
            runs.append({"path": o["path"], "fit_name": o.get("fit_name"), **o["fit"],
                         "status": o["status"], "seconds": o.get("seconds"), "worker": o.get("worker")})
        else:
            runs.append({"path": o["path"], "status": "failed", "reason": o["reason"], "error": o["error"],
                         "exit_code": o["exit_code"], "seconds": o.get("seconds"), "worker": o.get("worker")})
    failed = sum(not o["ok"] for o in batch.outcomes)
    return {"runs": runs, "batch": {"runs": len(runs), "fitted": len(runs) - failed, "failed": failed,
                                    "seconds": batch.seconds, "where": batch.where, "scheduler": batch.scheduler,
                                    "jobs": batch.jobs, "exit_code": int(exit_code(batch))}}


def print_failures(batch: Batch, stream=None) -> None:
    stream = stream or sys.stderr
    for line in failure_lines(batch):
        print(line, file=stream)
