"""What a batch prints: the per-run table, one line per failed or refused run, the JSON document, the exit code."""

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
        word = "REFUSED" if _refused(o) else "FAILED"
        return f"{name:<32} {word + ' ' + o['reason']:<16}{'-':>5}{'-':>10}{'-':>13}{'-':>9}{'-':>5}{'-':>8}{t}"
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


def _refused(o: dict) -> bool:
    """A run refused before its fit (open for writing, damaged: velab.batch.task.REFUSALS), not failed."""
    return not o["ok"] and o.get("status") == "refused"


def counts(batch: Batch) -> dict:
    """``{fitted, refused, failed}``: how many runs gave a fit, were refused before it, failed."""
    refused = sum(_refused(o) for o in batch.outcomes)
    failed = sum(not o["ok"] for o in batch.outcomes) - refused
    return {"fitted": len(batch.outcomes) - refused - failed, "refused": refused, "failed": failed}


def _num(v) -> float:
    return float(v) if isinstance(v, (int, float)) else math.nan


def table(batch: Batch) -> str:
    """One line per run (the best model, its wave speed, F and F / the record's noise, the runner-up and its
    delta AIC, the fit's warning codes), then a total (the refused runs counted when there are any)."""
    lines = [_HEAD, *(_row(o) for o in batch.outcomes)]
    c = counts(batch)
    n = len(batch.outcomes)
    refused = f", {c['refused']} refused" if c["refused"] else ""
    lines.append(f"{n} run{'s' if n != 1 else ''}: {c['fitted']} fitted, {c['failed']} failed{refused}, "
                 f"{batch.seconds:.1f} s ({batch.where})")
    return "\n".join(lines)


def failure_lines(batch: Batch) -> list[str]:
    """``velab: FAILED PATH (reason): what went wrong``, one line per failed run; ``velab: REFUSED PATH
    (reason): why`` for a refused one."""
    return [f"velab: {'REFUSED' if _refused(o) else 'FAILED'} {one_line(o['path'])} ({o['reason']}): "
            f"{one_line(o['error'])}" for o in batch.outcomes if not o["ok"]]


def json_doc(batch: Batch) -> dict:
    """``{runs: [...], batch: {...}}``: a fitted run is the single-run document (the fit's ``to_dict()``
    plus ``path`` and ``fit_name``) with its ``status`` and ``seconds``; a failed run is
    ``{path, status: "failed", reason, error, exit_code}``, a refused one the same with ``status: "refused"``."""
    runs = []
    for o in batch.outcomes:
        if o["ok"]:
            runs.append({"path": o["path"], "fit_name": o.get("fit_name"), **o["fit"],
                         "status": o["status"], "seconds": o.get("seconds"), "worker": o.get("worker")})
        else:
            runs.append({"path": o["path"], "status": "refused" if _refused(o) else "failed", "reason": o["reason"],
                         "error": o["error"], "exit_code": o["exit_code"], "seconds": o.get("seconds"),
                         "worker": o.get("worker")})
    return {"runs": runs, "batch": {"runs": len(runs), **counts(batch),
                                    "seconds": batch.seconds, "where": batch.where, "scheduler": batch.scheduler,
                                    "jobs": batch.jobs, "exit_code": int(exit_code(batch))}}


def print_failures(batch: Batch, stream=None) -> None:
    stream = stream or sys.stderr
    for line in failure_lines(batch):
        print(line, file=stream)
