"""Time one model evaluation: band-limited vs full-band frequency model vs MOC.

Run as ``python benchmarks/model_eval.py``. Reference case: Perugia rig,
material A (S3), 1 kHz sampling, records of 10, 20, 40 and 80 s from the trigger.

What is timed (best of several repeats, time.perf_counter):

* band    -- ``ValveHeadModel(rig, t, band_hz="auto")`` built once, ``head(A)`` timed:
             the cost of one objective evaluation in a calibration;
* full    -- the same with ``band_hz=None`` (every FFT bin), built once, ``head(A)`` timed;
* full+build -- ``valve_head(t, rig, A)``: construction (flow FFT) included;
* moc     -- ``moc_head(rig, a, J', tau, t)``: the compiled time-domain model on the
             sample grid, the rig's quadratic friction, default MOC step (2 ms), the
             trigger step from the frequency model included: one evaluation of the
             nonlinear calibration model.

Then, at 20 s, the MOC variants against the MOC as it was before compilation (the
vectorised numpy loop of Covas's first-order scheme, reproduced below as the
baseline) and the straightforward numpy implementation of the present scheme
(tests/moc_reference.py), all measured in this run, with their accuracy against the
full-band frequency model (linear friction, where both are exact).
No assertions: timings depend on the machine; read the ratios.
"""

from __future__ import annotations

import platform
import sys
import time
from pathlib import Path

import numpy as np

from velab.config import load_material, load_rig
from velab.rig import GRAVITY_M_S2
from velab.model import ValveHeadModel, creep_scale, flow_perturbation, valve_head
from velab.moc import moc_head, moc_solve, warm_up

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from moc_reference import march_reference  # noqa: E402 - the numpy reference of the present scheme

DT_S = 1e-3
RECORDS_S = (10.0, 20.0, 40.0, 80.0)


def best_time(fn, budget_s: float = 1.0, min_repeats: int = 3, max_repeats: int = 200) -> float:
    """Minimum wall time of fn() over repeats; repeats until ~budget_s spent (at least min_repeats)."""
    times = []
    start = time.perf_counter()
    while len(times) < max_repeats:
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
        if len(times) >= min_repeats and time.perf_counter() - start > budget_s:
            break
    return min(times)


def fmt_ms(s: float) -> str:
    return f"{s * 1e3:10.2f}"


def legacy_numpy_moc(rig, J_rel, tau, t_end_s, dt_s, a):
    """The MOC as velab had it before the compiled kernel (Covas's scheme: creep rate at the
    new node, explicit tangent friction), vectorised over nodes with numpy. Baseline only."""
    n_reach = max(2, int(round(rig.pipe.length_m / (a * dt_s))))
    dt = rig.pipe.length_m / (n_reach * a)
    n_steps = int(np.floor(t_end_s / dt + 1e-9)) + 1
    B = a / (GRAVITY_M_S2 * rig.pipe.area_m2)
    adt_R = a * dt * rig.linear_resistance
    J_rel, tau = J_rel[:, None], tau[:, None]
    e_k = np.exp(-dt / tau)
    G = float(np.sum(J_rel * (1 - e_k)))
    c_hold = J_rel * (tau * (1 - e_k) / dt - e_k)
    c_hnew = J_rel * (1 - tau * (1 - e_k) / dt)
    q_valve = flow_perturbation(np.arange(n_steps) * dt, rig)
    h, q = np.zeros(n_reach + 1), np.zeros(n_reach + 1)
    eps = np.zeros((J_rel.shape[0], n_reach + 1))
    head = np.empty(n_steps)
    h_new, q_new = np.empty_like(h), np.empty_like(q)
    for n in range(n_steps):
        fr = adt_R * q
        cp = h[:-1] + B * q[:-1] - fr[:-1]
        cm = h[1:] - B * q[1:] + fr[1:]
        c0 = c_hold * h + e_k * eps
        S = -dt * np.sum(c0 / tau, axis=0)
        cpi, cmi = cp[:-1] - S[1:-1], cm[1:] - S[1:-1]
        h_new[1:-1] = (cpi + cmi) / (2 * (1 + G))
        q_new[1:-1] = (cpi - cmi) / (2 * B)
        h_new[0] = 0.0
        q_new[0] = -(cm[0] - S[0]) / B
        q_new[-1] = q_valve[n]
        h_new[-1] = (cp[-1] - S[-1] - B * q_valve[n]) / (1 + G)
        eps = c_hnew * h_new + c0
        h, h_new = h_new, h
        q, q_new = q_new, q
        head[n] = h[-1]
    return np.arange(n_steps) * dt, head


def main() -> None:
    rig = load_rig("perugia")
    mat = load_material("A")
    a = mat.wave_speed_m_s
    J = np.array([e.J_per_pa for e in mat.elements]) * creep_scale(rig, a)
    tau = np.array([e.tau_s for e in mat.elements])
    t0 = time.perf_counter()
    warm_up()
    t_warm = time.perf_counter() - t0
    print(f"velab model evaluation benchmark -- rig {rig.name!r}, material {mat.name} ({mat.model_name}), "
          f"dt = {DT_S * 1e3:g} ms, friction {rig.friction}")
    print(f"python {platform.python_version()}, numpy {np.__version__}, {platform.machine()}; "
          f"MOC kernel compile-or-load {t_warm:.2f} s")
    print()
    header = (f"{'record s':>8} {'samples':>8} {'bins band/full':>15} {'band ms':>10} {'full ms':>10} "
              f"{'full+build':>10} {'moc ms':>10} {'full/band':>9} {'moc/band':>9}")
    print(header)
    print("-" * len(header))
    rows = []
    for T in RECORDS_S:
        t = np.arange(int(round(T / DT_S)) + 1) * DT_S
        band = ValveHeadModel(rig, t, band_hz="auto")
        full = ValveHeadModel(rig, t, band_hz=None)
        tb = best_time(lambda: band.head(mat))
        tf = best_time(lambda: full.head(mat))
        tfb = best_time(lambda: valve_head(t, rig, mat))
        tm = best_time(lambda: moc_head(rig, a, J, tau, t))
        rows.append((T, tb, tf, tm))
        print(f"{T:8.0f} {t.size:8d} {band.band.n_bins:7d}/{full.band.n_bins:<7d} {fmt_ms(tb)} {fmt_ms(tf)} "
              f"{fmt_ms(tfb)} {fmt_ms(tm)} {tf / tb:9.1f} {tm / tb:9.0f}")

    # growth with record length, relative to the 10 s record
    print()
    print("growth relative to the 10 s record (x record length):")
    T0, b0, f0, m0 = rows[0]
    for T, tb, tf, tm in rows:
        print(f"  {T:5.0f} s ({T / T0:3.0f}x): band {tb / b0:5.1f}x   full {tf / f0:5.1f}x   moc {tm / m0:5.1f}x")

    # the MOC at 20 s: compiled variants vs the numpy loops, and accuracy
    T = 20.0
    t = np.arange(int(round(T / DT_S)) + 1) * DT_S
    lin = rig.with_changes(friction="linear")
    band = ValveHeadModel(rig, t, band_hz="auto")
    tb = best_time(lambda: band.head(mat))
    t_old = best_time(lambda: legacy_numpy_moc(lin, J, tau, T, 1e-3, a), budget_s=2.0, min_repeats=2)
    n = int(round(rig.pipe.length_m / (a * 1e-3)))
    dt1 = rig.pipe.length_m / (n * a)
    q1 = flow_perturbation(np.arange(int(T / dt1) + 1) * dt1, rig)
    t_ref = best_time(lambda: march_reference(lin, J, tau, q1, n, dt1, a, "linear", "none"), budget_s=2.0,
                      min_repeats=1)
    cases = [
        ("moc_solve, 1 ms, linear", lambda: moc_solve(lin, mat, T, 1e-3, valve="imposed")),
        ("moc_head, 2 ms, linear", lambda: moc_head(lin, a, J, tau, t)),
        ("moc_head, 2 ms, quadratic", lambda: moc_head(rig, a, J, tau, t)),
        ("moc_head, 1 ms, quadratic", lambda: moc_head(rig, a, J, tau, t, dt_s=1e-3)),
        ("moc_head, 2 ms, quadratic + vardy-brown", lambda: moc_head(rig, a, J, tau, t, unsteady="vardy-brown")),
        ("moc_head, 2 ms, quadratic + brunone", lambda: moc_head(rig, a, J, tau, t, unsteady="brunone")),
    ]
    print()
    print(f"MOC at {T:g} s (baselines measured in this run: band-limited model {tb * 1e3:.2f} ms; numpy MOC "
          f"before compilation {t_old * 1e3:.0f} ms; numpy reference of the present scheme {t_ref * 1e3:.0f} ms):")
    print(f"  {'variant':<42} {'ms':>8} {'/band':>7} {'old numpy/x':>11} {'reference/x':>11}")
    for name, fn in cases:
        tm = best_time(fn)
        print(f"  {name:<42} {fmt_ms(tm)[2:]:>8} {tm / tb:7.0f} {t_old / tm:11.1f} {t_ref / tm:11.1f}")

    ref = valve_head(t, lin, mat)
    hj = rig.joukowsky_head_m(a)
    print()
    print(f"accuracy at {T:g} s against the full-band frequency model, linear friction (Joukowsky head {hj:.3f} m):")
    d = band.head(mat) - valve_head(t, rig, mat)
    print(f"  band 'auto'          : max {np.abs(d).max():.4f} m, RMS {np.sqrt(np.mean(d**2)):.5f} m")
    r = moc_solve(lin, mat, T, 1e-3, valve="imposed")
    d = r.head_m - valve_head(np.arange(int(40.0 / r.dt_s)) * r.dt_s, lin, mat)[: r.t_s.size]
    print(f"  moc_solve 1 ms (grid): max {np.abs(d).max():.5f} m = {np.abs(d).max() / hj:.1e} hJ, "
          f"RMS {np.sqrt(np.mean(d**2)):.6f} m")
    tl, hl = legacy_numpy_moc(lin, J, tau, T, 1e-3, a)
    d = hl - valve_head(np.arange(int(40.0 / (tl[1] - tl[0]))) * (tl[1] - tl[0]), lin, mat)[: tl.size]
    print(f"  old numpy MOC 1 ms   : max {np.abs(d).max():.5f} m = {np.abs(d).max() / hj:.1e} hJ, "
          f"RMS {np.sqrt(np.mean(d**2)):.6f} m")
    for dt in (1e-3, 2e-3, 4e-3):
        d = moc_head(lin, a, J, tau, t, dt_s=dt) - ref
        print(f"  moc_head {dt * 1e3:g} ms        : max {np.abs(d).max():.5f} m = {np.abs(d).max() / hj:.1e} hJ, "
              f"RMS {np.sqrt(np.mean(d**2)):.6f} m")


if __name__ == "__main__":
    main()
