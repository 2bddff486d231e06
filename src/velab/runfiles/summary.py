"""What a run file holds, as plain data (``as_dict``) and as readable text (``describe``).

Used by ``velab info`` (text and ``--json``) and the GUI's archive page; reading goes
through :func:`velab.runfiles.read_run` and :func:`velab.runfiles.open_run_file`, so a
damaged file is one ``DataError`` line.
"""

from __future__ import annotations

import math

import h5py
import numpy as np

from velab.runfiles.fits import read_fit_dict
from velab.runfiles.reader import Run, open_run_file


def as_dict(r: Run) -> dict:
    h = r.head_m[np.isfinite(r.head_m)]
    return {
        "path": str(r.path), "file_name": r.file_name, "title": r.title, "status": r.status,
        "status_reason": r.status_reason, "incomplete": r.incomplete, "open_for_write": r.open_for_write,
        "damaged": r.damage or None,
        "start_time": r.start_time, "end_time": r.end_time, "format_version": r.format_version,
        "velab_version": r.velab_version, "n_samples": r.n_samples, "sample_rate_hz": r.sample_rate_hz,
        "trigger_time_s": r.trigger_time_s, "duration_after_trigger_s": r.duration_after_trigger_s,
        "steady_head_m": r.steady_head_m, "max_head_m": float(h.max()) if h.size else None,
        "min_head_m": float(h.min()) if h.size else None, "nan_samples": int(np.count_nonzero(~np.isfinite(r.head_m))),
        "channels": dict(r.channel_units), "rig": r.rig.to_dict(), "manoeuvre": r.manoeuvre,
        "material": r.material.to_dict() if r.material is not None else None, "noise_std_m": r.noise_std_m,
        "events": [{"time_s": t, "kind": k, "message": m} for t, k, m in r.events],
        "gaps": [{"sample_index": i, "lost": c} for i, c in r.gaps], "source": r.source, "versions": r.versions,
        "fits": read_fits(r.path),
    }


def describe(r: Run) -> str:
    lines = [f"{r.path}"]
    if r.damage:  # first: what is shown below is what is left of a run velab will not write into
        lines.append(f"  DAMAGED      {r.damage}: read-only (velab fit --no-save only)")
    status = r.status
    if r.damage and "no /entry/status" in r.damage:
        status = "(none stored)"
    elif r.incomplete:
        status = "INCOMPLETE (the recording never closed the file: crash or kill; data up to the last flush)"
        if r.status_reason:
            status += f"; {r.status_reason}"
    elif r.status_reason:
        status = f"{r.status} ({r.status_reason})"
    if r.open_for_write:
        status += " [flagged open for writing: read-only until `velab recover`]"
    lines.append(f"  title        {r.title}")
    lines.append(f"  status       {status}")
    lines.append(f"  started      {r.start_time}" + (f"   ended {r.end_time}" if r.end_time else ""))
    pre = float(np.count_nonzero(r.time_s < r.trigger_time_s)) / r.sample_rate_hz if r.sample_rate_hz else 0.0
    lines.append(f"  samples      {r.n_samples} at {r.sample_rate_hz:g} Hz: {pre:.3f} s before the trigger, "
                 f"{r.duration_after_trigger_s:.3f} s after")
    h = r.head_m[np.isfinite(r.head_m)]
    if h.size:
        lines.append(f"  head         steady {r.steady_head_m:.3f} m, max {h.max():.3f} m, min {h.min():.3f} m "
                     f"(surge {h.max() - r.steady_head_m:.3f} m)")
    n_nan = int(np.count_nonzero(~np.isfinite(r.head_m)))
    if n_nan:
        lines.append(f"  NaN samples  {n_nan}")
    for name in r.channels:
        lines.append(f"  channel      {name} [{r.channel_units.get(name, '')}]")
    rig = r.rig
    p = rig.pipe
    lines.append(f"  rig          {rig.name}: L {p.length_m:g} m, D {p.inner_diameter_m * 1e3:g} mm, "
                 f"e {p.wall_thickness_m * 1e3:g} mm, alpha {p.constraint_alpha:g}, Q0 {rig.steady_flow_m3_s * 1e3:g} l/s")
    lines.append(f"  friction     {rig.friction_description}")
    lines.append(f"  valve        {rig.valve.describe()}")
    lines.append(f"  manoeuvre    beta {rig.manoeuvre.beta_per_s:g} 1/s, gamma {rig.manoeuvre.gamma:g} "
                 f"(closure 90->10 % in {rig.manoeuvre.closure_time_s:.3f} s)"
                 + (f", end position {r.manoeuvre['end_position']:g} %" if "end_position" in r.manoeuvre else ""))
    if r.material is not None:
        m = r.material
        els = ", ".join(f"(E {el.E_pa:.3g} Pa, eta {el.eta_pa_s:.3g} Pa s, tau {el.tau_s:.3g} s)" for el in m.elements)
        lines.append(f"  material     {m.name} ({m.model_name}, truth): a {m.wave_speed_m_s:g} m/s {els}")
    if r.noise_std_m is not None:
        lines.append(f"  noise        {r.noise_std_m:g} m (synthetic)")
    if r.gaps:
        lost = sum(c for _, c in r.gaps)
        lines.append(f"  gaps         {len(r.gaps)} gaps, {lost} samples lost (not interpolated)")
    if r.events:
        lines.append(f"  events       {len(r.events)}")
        for t, kind, msg in r.events[:20]:
            lines.append(f"    {t:9.3f} s  {kind:<12} {msg}")
        if len(r.events) > 20:
            lines.append(f"    ... {len(r.events) - 20} more")
    lines.append(f"  format       {r.format_version} (velab {r.velab_version})")
    lines.extend(describe_fits(r.path))
    return "\n".join(lines)


def read_fits(path) -> dict:
    """name -> stored fit (plain data); a fit group that cannot be read -> {"error": ...}."""
    out = {}
    with open_run_file(path) as fh:
        fits = fh["entry"].get("fits")
        if not isinstance(fits, h5py.Group):
            return out
        for name, g in fits.items():
            if isinstance(g, h5py.Group):
                try:
                    out[name] = read_fit_dict(g)
                except Exception as exc:  # noqa: BLE001 - one damaged fit group must not hide the run
                    out[name] = {"error": f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"}
    return out


def describe_fits(path) -> list[str]:
    fits = read_fits(path)
    if not fits:
        return ["  fits         none (run `velab fit` on this file)"]
    out = []
    for name, d in fits.items():
        if "error" in d:
            out.append(f"  fit {name}: unreadable ({d['error']})")
            continue
        window = d.get("window", math.nan)
        out.append(f"  fit {name}: method {d.get('method', '?')}, window {float(window):g} s, "
                   f"n {int(d.get('n', 0))}, best {d.get('best', '?')} ({d.get('date', '')})")
        # the fit's warnings (velab.fitting.adequacy: misfit, cavitation, bound); older fits have none stored
        for w in d.get("warnings") or []:
            if isinstance(w, dict):
                out.append(f"    WARNING {w.get('code', '?')}: {w.get('message', '')}")
        if isinstance(d.get("baseline_noise_m"), (int, float)):
            out.append(f"    record noise {float(d['baseline_noise_m']):.3g} m (pretrigger baseline); "
                       "F/noise per model below")
        out.append(f"    {'model':<6}{'k':>3}{'F (m^2)':>13}{'F/noise':>9}{'AIC':>14}{'dAIC':>12}{'weight':>8}  {'a (m/s)':>8}"
                   "  support")
        for m in d.get("models", []):
            def num(key):
                v = m.get(key, math.nan)
                return float(v) if isinstance(v, (int, float)) else math.nan
            out.append(f"    {str(m.get('name', '?')):<6}{int(num('k')) if math.isfinite(num('k')) else 0:>3}"
                       f"{num('F'):>13.5g}{num('noise_ratio'):>9.3g}{num('aic'):>14.2f}{num('delta_aic'):>12.2f}{num('weight'):>8.3f}  "
                       f"{num('wave_speed'):>8.2f}  {m.get('support', '')}")
        best = next((m for m in d.get("models", []) if m.get("name") == d.get("best")), {})
        offset = best.get("steady_head_offset")
        if isinstance(offset, (int, float)) and offset != 0.0 and math.isfinite(offset):
            # (fits stored before velab.fitting.offset have none: the baseline's mean was the steady head)
            out.append(f"    steady head: {best['name']} fits the baseline's mean {1e3 * offset:+.3g} mm off "
                       "(every model fits this offset, the baseline its prior)")
    return out
