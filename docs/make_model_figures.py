"""Figures of docs/model.md: what the friction laws change on the two reference rigs.

Run as ``python docs/make_model_figures.py`` (writes docs/img/friction-laws.png and
prints the numbers quoted in docs/model.md). Material A's wall on both rigs (on the
imperial rig with its nominal wave speed), 20 s at 1 kHz, velab.moc.moc_head.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from velab.config import load_material, load_rig  # noqa: E402
from velab.model import creep_scale  # noqa: E402
from velab.moc import moc_head  # noqa: E402

OUT = Path(__file__).resolve().parent / "img" / "friction-laws.png"
LAWS = [("linear", "none", "linear (tangent R, the paper's)"), ("quadratic", "none", "quadratic"),
        ("quadratic", "vardy-brown", "quadratic + Vardy-Brown"), ("quadratic", "brunone", "quadratic + Brunone k3 0.02")]


def heads(rig_name):
    rig = load_rig(rig_name)
    a = rig.nominal_wave_speed_m_s
    els = load_material("A").elements
    J = np.array([e.J_per_pa for e in els]) * creep_scale(rig, a)
    tau = np.array([e.tau_s for e in els])
    t = np.arange(20000) * 1e-3
    return rig, t, {label: moc_head(rig, a, J, tau, t, friction=f, unsteady=u) for f, u, label in LAWS}


def rms(x):
    return float(np.sqrt(np.mean(x**2)))


def main() -> None:
    fig, axes = plt.subplots(2, 2, figsize=(12, 7.5), sharex=True)
    for row, name in enumerate(("perugia", "imperial")):
        rig, t, h = heads(name)
        ref = h[LAWS[1][2]]
        print(f"{rig.name}: hJ {rig.joukowsky_head_m():.2f} m, steady head loss {rig.steady_head_loss_m:.3f} m, "
              f"R L Q0 {rig.linear_resistance * rig.pipe.length_m * rig.steady_flow_m3_s:.3f} m")
        for label, y in h.items():
            axes[row, 0].plot(t, y, lw=0.7, label=label)
            if y is not ref:
                d = y - ref
                axes[row, 1].plot(t, d, lw=0.7, label=f"{label} - quadratic")
                print(f"  {label:<32} - quadratic: RMS {rms(d):.2f} m, max {np.abs(d).max():.2f} m, "
                      f"RMS 0-0.6 s {rms(d[t < 0.6]):.2f} m, 5-10 s {rms(d[(t > 5) & (t < 10)]):.2f} m")
            late = t > 15
            print(f"  {label:<32} peak-to-peak at 15-20 s: {np.ptp(y[late]):.2f} m")
        axes[row, 0].set_ylabel(f"{name}: head above steady (m)")
        axes[row, 1].set_ylabel("difference from quadratic (m)")
    for ax in axes.flat:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper right")
    for ax in axes[1]:
        ax.set_xlabel("time from the trigger (s)")
    fig.suptitle("Material A's S3 wall: head at the valve with each friction law (velab.moc.moc_head)")
    fig.tight_layout()
    fig.savefig(OUT, dpi=110)
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
