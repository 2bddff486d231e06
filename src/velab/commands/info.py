"""``velab info``: a readable summary of a run file and its fits."""

from __future__ import annotations

import argparse

import h5py
import numpy as np

from velab.runfile import Run, _str, open_run_file, read_run


def register(sub) -> None:
    p = sub.add_parser("info", help="summarise a run file and its fits",
                       description="Print what a run file holds: status, timing, rig, material, events, gaps, fits.")
    p.add_argument("runs", nargs="+", help="run files (.h5)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    for i, path in enumerate(args.runs):
        if i:
            print()
        print(describe(read_run(path)))
    return 0


def describe(r: Run) -> str:
    lines = [f"{r.path}"]
    status = r.status
    if r.incomplete:
        status = "INCOMPLETE (the recording never closed the file: crash or kill; data up to the last flush)"
        if r.status_reason:
            status += f"; {r.status_reason}"
    elif r.status_reason:
        status = f"{r.status} ({r.status_reason})"
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
    for name, values in r.channels.items():
        lines.append(f"  channel      {name} [{r.channel_units.get(name, '')}]")
    rig = r.rig
    p = rig.pipe
    lines.append(f"  rig          {rig.name}: L {p.length_m:g} m, D {p.inner_diameter_m * 1e3:g} mm, "
                 f"e {p.wall_thickness_m * 1e3:g} mm, alpha {p.constraint_alpha:g}, Q0 {rig.steady_flow_m3_s * 1e3:g} l/s")
    lines.append(f"  friction     {rig.friction_description}")
    lines.append(f"  manoeuvre    beta {rig.manoeuvre.beta_per_s:g} 1/s, gamma {rig.manoeuvre.gamma:g} "
                 f"(closure 90->10 % in {rig.manoeuvre.closure_time_s:.3f} s)")
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


def describe_fits(path) -> list[str]:
    out = []
    with open_run_file(path) as fh:
        fits = fh["entry"].get("fits")
        if fits is None or not len(fits):
            return ["  fits         none (run `velab fit` on this file)"]
        for name, g in fits.items():
            if not isinstance(g, h5py.Group):
                continue
            a = g.attrs
            out.append(f"  fit {name}: method {_str(a.get('method', '?'))}, window {float(a.get('window_s', np.nan)):g} s, "
                       f"n {int(a.get('n', 0))}, best {_str(a.get('best_model', '?'))} ({_str(a.get('date', ''))})")
            out.append(f"    {'model':<6}{'k':>3}{'F (m^2)':>13}{'AIC':>14}{'dAIC':>12}{'weight':>8}  {'a (m/s)':>8}  support")
            models = [(k, v) for k, v in g.items() if isinstance(v, h5py.Group)]
            models.sort(key=lambda kv: int(kv[1].attrs.get("m", 0)))
            for mname, mg in models:
                ma = mg.attrs
                out.append(
                    f"    {mname:<6}{int(ma.get('k', 0)):>3}{float(ma.get('F', np.nan)):>13.5g}{float(ma.get('aic', np.nan)):>14.2f}"
                    f"{float(ma.get('delta_aic', np.nan)):>12.2f}{float(ma.get('weight', np.nan)):>8.3f}  "
                    f"{float(ma.get('wave_speed_m_s', np.nan)):>8.2f}  {_str(ma.get('support', ''))}"
                )
    return out
