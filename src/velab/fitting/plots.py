"""Report figures of a calibration, after the paper's Figures 2-5 (matplotlib, no GUI)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from velab.rig import Rig
from velab.fitting.creep import creep_curve, creep_of
from velab.fitting.residuals import best_residuals
from velab.fitting.selection import averaged_creep_shown
from velab.fitting.results import SweepResult
from velab.fitting.friction import fitted_head
from velab.fitting.flows import result_flow
from velab.model import phi


def averaged_band(ax, result):
    """The model-averaged creep's 95 % band, hatched, on ``ax`` where the choice of model is uncertain
    (velab.fitting.creep.averaged_creep_shown); the artist, or None."""
    avg = averaged_creep_shown(result)
    if avg is None:
        return None
    c = avg.curve
    ok = c.J_per_pa > 0
    return ax.fill_between(c.t_s[ok], c.lower[ok], c.upper[ok], facecolor="none", edgecolor="0.35", hatch="///",
                           lw=0.0, label="model-averaged 95 % band", zorder=1)


# Burnham and Anderson's reading of delta AIC, the lines of the delta AIC panel
DAIC_LINES = ((2.0, ":", "ΔAIC = 2: substantial support below"), (10.0, "--", "ΔAIC = 10: essentially none above"))


def figure_title(result, rig: Rig | None = None, run=None, runs: int = 1) -> str:
    """What makes a printout traceable: the run (file, title), the rig, the date recorded, the best model."""
    parts = []
    if run is not None:
        name = Path(str(getattr(run, "path", "") or "")).name
        title = getattr(run, "title", "") or ""
        parts.append(name + (f" ({title})" if title else ""))
        start = str(getattr(run, "start_time", "") or "")
        if start:
            parts.append("recorded " + start[:19].replace("T", " "))
    elif runs > 1:
        parts.append(f"joint fit of {runs} runs")
    if rig is not None:
        parts.append(f"rig {getattr(rig, 'name', '') or '?'}")
    best = result.best
    fit = f"best model {best.name} of {len(result.models)} (window {result.window_s:g} s, n = {result.n})"
    return " — ".join(parts) + "\n" + fit if parts else fit


def report_figure(t, h, rig: Rig, result: SweepResult, path, position_pct=None, run=None):
    """Write a figure: measured vs fitted head; delta AIC vs m; the retarded creep compliance J(t) - J0
    of every model with the best one's 95 % band (velab.fitting.creep); |phi(omega)|; and across the
    bottom the best model's residuals against time with the record's noise band (+- the pretrigger
    baseline's standard deviation, velab.fitting.adequacy) and the fit's warnings.

    The format follows the file suffix (.png, .pdf, .svg). The models are driven by the fit's own flow
    at the valve (``position_pct``: the recorded valve position on t, if the fit took it). Titled with the
    run (``run``: the run file read, for its name, title and start), the rig, the date and the best model.
    Returns the matplotlib Figure.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 11), layout="constrained")
    axes = fig.subplot_mosaic([["head", "aic"], ["creep", "phi"], ["res", "res"]], height_ratios=[1, 1, 0.8])
    ax = np.array([[axes["head"], axes["aic"]], [axes["creep"], axes["phi"]]])
    t = np.asarray(t, dtype=float)
    h = np.asarray(h, dtype=float)
    full = [f for f in result.models if not f.reduced]
    best = result.best
    flow = result_flow(result.settings, t, h, rig, position_pct)
    fig.suptitle(figure_title(result, rig, run), fontsize=10)

    a0 = ax[0, 0]
    a0.plot(t, h, color="0.6", lw=0.6, label="measured")
    for f in full:
        if f.m in (1, 2, 3) or f is best:
            a0.plot(t, fitted_head(t, rig, f, flow=flow), lw=0.9, label=f"{f.name} (F={f.F:.3g} m²)")
    a0.set_xlabel("t from the trigger (s)")
    a0.set_ylabel("h − h_steady (m)")
    a0.set_title("measured and calibrated head, minus the steady head")
    a0.legend(fontsize=7)

    a1 = ax[0, 1]
    # 1 + delta AIC on a log axis, labelled in delta AIC: the best model's 0 has a place (a log axis has none)
    for red, mk in ((False, "o"), (True, "s")):
        sel = [f for f in result.models if f.reduced == red]
        if sel:
            a1.plot([f.m for f in sel], [1.0 + max(f.delta_aic, 0.0) for f in sel], mk + "-",
                    label="reduced models" if red else "models EL, S1..")
    a1.plot([best.m], [1.0 + max(best.delta_aic, 0.0)], "*", ms=12, color="tab:green", label=f"best: {best.name}")
    a1.set_yscale("log")
    top = max([1.0 + max(f.delta_aic, 0.0) for f in result.models] + [20.0])
    ticks = [v for v in (0, 2, 10, 100, 1e3, 1e4, 1e5, 1e6, 1e7) if 1 + v <= top * 1.5]
    a1.set_yticks([1 + v for v in ticks], [f"{v:g}" for v in ticks])
    a1.minorticks_off()
    for level, ls, label in DAIC_LINES:
        a1.axhline(1 + level, color="0.5", ls=ls, lw=0.9, label=label)
    a1.set_xlabel("m (Kelvin-Voigt elements)")
    a1.set_ylabel("ΔAIC (log scale of 1 + ΔAIC)")
    a1.set_title(f"ΔAIC against m ({_criterion(result)})")
    a1.legend(fontsize=7)

    a2 = ax[1, 0]
    for f in full:
        if not f.m or all(f.negligible or (False,)):
            continue  # a model whose every element vanished: ~1e-25 1/Pa, ten decades below the others
        c = creep_of(result, f)
        ok = c.J_per_pa > 0
        line, = a2.loglog(c.t_s[ok], c.J_per_pa[ok], lw=2.0 if f is best else 0.9, label=f.name,
                          zorder=3 if f is best else 2)
        if f is best and c.has_band:
            a2.fill_between(c.t_s[ok], c.lower[ok], c.upper[ok], color=line.get_color(), alpha=0.25, lw=0,
                            label=f"{f.name} 95 % band")
        if f is best:  # the elements' retardation times on the best curve
            tau = np.array([t for t, neg in zip(f.tau_s, f.negligible or (False,) * f.m) if not neg])
            tau = tau[(tau >= c.t_s[0]) & (tau <= c.t_s[-1])] if c.t_s.size else tau[:0]
            if tau.size:
                a2.plot(tau, creep_curve(f, tau).J_per_pa, "o", ms=4, color=line.get_color())
    averaged_band(a2, result)
    a2.set_xlabel("t (s)")
    a2.set_ylabel("J(t) − J0 (1/Pa)")
    a2.set_title(f"retarded creep compliance (dots: {best.name}'s τ_k)")
    if a2.lines:
        a2.legend(fontsize=7)

    a3 = ax[1, 1]
    omega = 2 * np.pi * np.logspace(-2, 2, 300)
    for f in full:
        if f.m:
            a3.loglog(omega / (2 * np.pi), np.abs(phi(omega, rig, f.material())), label=f.name)
    a3.set_xlabel("f (Hz)")
    a3.set_ylabel("|φ(iω)|")
    a3.set_title("viscoelastic function")
    a3.legend(fontsize=7)

    a4 = axes["res"]
    tr, res = best_residuals(t, h, rig, result, position_pct=position_pct)
    a4.plot(tr, res, color="0.3", lw=0.5, label=f"{best.name} residual (at the fit rate)")
    sd = result.baseline_noise_m
    if sd is not None and len(tr):  # the band over the data only, not past it
        span = [float(tr[0]), float(tr[-1])]
        a4.fill_between(span, [-sd, -sd], [sd, sd], color="tab:green", alpha=0.2, lw=0,
                        label=f"± 1 SD of the baseline noise ({sd:.3g} m)")
        for k in (-2, 2):
            a4.plot(span, [k * sd, k * sd], color="tab:green", lw=0.6, ls=":", label="± 2 SD" if k > 0 else None)
    if len(tr):
        a4.set_xlim(float(tr[0]), float(tr[-1]))
    ratio = f", F/noise {best.noise_ratio:.3g}" if best.noise_ratio is not None else ", no baseline noise"
    codes = ", ".join(w["code"] for w in result.warnings)
    a4.set_title(f"residuals of {best.name}{ratio}" + (f"   WARNING: {codes}" if codes else ""),
                 color="tab:red" if codes else "black")
    a4.set_xlabel("t from the trigger (s)")
    a4.set_ylabel("h − model (m)")
    a4.legend(fontsize=7, loc="upper right")
    fig.savefig(path)
    return fig


def _criterion(result) -> str:
    return "AIC with AR(1) noise" if getattr(result, "selection", None) == "ar1" else "white-noise AIC"
