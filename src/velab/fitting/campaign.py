"""The campaign figure of a joint fit (issue 25 part 3): each run's creep against the joint one, and
each run's wave speed against its steady flow (matplotlib, no GUI; velab.fitting.joint)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from velab.fitting.creep import creep_of


def campaign_figure(result, path, sources=None):
    """Write the figure of a joint fit (a velab.fitting.joint.JointResult): left, J(t) - J0 of the best
    model's wall fitted on each run alone and the joint wall with its 95 % band; right, each run's own
    wave speed +- its standard error against the run's steady flow Q0, with the joint a +- SE. Runs that
    disagree with the joint wall (misfit) are drawn with open markers and named in the legend. The format
    follows the suffix (.png, .pdf, .svg). Titled with the runs (their number, the first and last file), the
    rig (``sources``: the CampaignRuns fitted), the dates they were recorded and the best model.
    Error bars and bands are 95 % (1.96 standard errors), and say so. Returns the matplotlib Figure."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    best = result.best
    fig = Figure(figsize=(12, 5.4), layout="constrained")
    fig.suptitle(_title(result, sources), fontsize=10)
    ax_c, ax_a = fig.subplots(1, 2)
    for i, r in enumerate(result.runs):
        c = (r.get("own") or {}).get("creep") or {}
        t, J = np.asarray(c.get("t_s") or [], dtype=float), np.asarray(c.get("J_per_pa") or [], dtype=float)
        ok = J > 0
        if ok.any():
            label = _run_label(r) + (" (disagrees)" if r.get("disagrees") else "")
            ax_c.loglog(t[ok], J[ok], lw=0.9, ls="--" if r.get("disagrees") else "-", label=label)
    joint = creep_of(result, best)
    ok = joint.J_per_pa > 0
    if ok.any():
        line, = ax_c.loglog(joint.t_s[ok], joint.J_per_pa[ok], color="k", lw=2.0, label=f"joint {best.name}")
        if joint.has_band:
            ax_c.fill_between(joint.t_s[ok], joint.lower[ok], joint.upper[ok], color="k", alpha=0.2, lw=0,
                              label="joint 95 % band")
    ax_c.set_xlabel("t (s)")
    ax_c.set_ylabel("J(t) − J0 (1/Pa)")
    ax_c.set_title(f"creep compliance: each run's {best.name} wall and the joint one")
    if ax_c.lines:
        ax_c.legend(fontsize=7)

    for r in result.runs:
        own = r.get("own") or {}
        q0 = 1e3 * float(r.get("steady_flow_m3_s", math.nan))
        a, se = float(own.get("wave_speed", math.nan)), float(own.get("wave_speed_se", math.nan))
        bad = bool(r.get("disagrees"))
        ax_a.errorbar([q0], [a], yerr=[1.96 * se] if math.isfinite(se) else None, fmt="o", capsize=3,
                      mfc="none" if bad else None, label=_run_label(r) + (" (disagrees)" if bad else ""))
    a, se = best.wave_speed_m_s, best.wave_speed_se_m_s
    ax_a.axhline(a, color="k", lw=1.5, label=f"joint a = {a:.2f} m/s"
                 + (f" ± {1.96 * se:.2g} (95 %)" if math.isfinite(se) else ""))
    if math.isfinite(se):
        ax_a.axhspan(a - 1.96 * se, a + 1.96 * se, color="k", alpha=0.15, lw=0, label="joint a, 95 % interval")
    ax_a.ticklabel_format(axis="y", useOffset=False)
    ax_a.set_xlabel("steady flow Q0 (l/s)")
    ax_a.set_ylabel("wave speed a (m/s); error bars 95 %")
    ax_a.set_title("wave speed per run against its steady flow")
    ax_a.legend(fontsize=7)
    fig.savefig(path)
    return fig


def _title(result, sources=None) -> str:
    """'joint fit of 4 runs (a.h5 … d.h5) — rig X — recorded 2026-11-20 … 2026-11-21' and the best model."""
    names = [_run_label(r) for r in result.runs]
    runs = f"joint fit of {len(names)} runs" + (f" ({names[0]} … {names[-1]})" if len(names) > 1 else "")
    parts = [runs]
    rig = getattr(getattr(sources[0], "rig", None), "name", "") if sources else ""
    if rig:
        parts.append(f"rig {rig}")
    days = sorted(d for d in (_recorded(r.get("path")) for r in result.runs) if d)
    if days:
        parts.append("recorded " + (days[0] if days[0] == days[-1] else f"{days[0]} … {days[-1]}"))
    best = result.best
    return " — ".join(parts) + f"\nbest model {best.name} of {len(result.models)} (window {result.window_s:g} s)"


def _recorded(path) -> str:
    """The day a run file was recorded (its /entry start_time), "" if it cannot be read."""
    try:
        import h5py

        from velab.runfiles import layout as L

        with h5py.File(str(path), "r") as f:
            return L.read_str(f["entry"], "start_time")[:10]
    except Exception:  # noqa: BLE001 - a title without the date rather than no figure
        return ""


def _run_label(r: dict) -> str:
    return Path(str(r.get("path", "?"))).name
