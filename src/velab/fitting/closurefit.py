"""The closure search: a head-only record's closure fitted as nuisance parameters on its first part.

No position record (imported CSVs): the effective opening is the closure family (velab.fitting.closure),
fitted on the record's first part (``early_window_s``: the closure and the first wave periods it shapes)
jointly with a one-element wall (which stands in for whatever wall the sweep then finds: the closure's
parameters barely depend on it), through the same friction correction as the sweep (the time-domain model at
the current parameters, velab.fitting.friction). ``choose_closure`` holds the shape at the valve the rig file
describes unless the record's first part shows another (``SHAPE_PRICE``); the closure is the same for every
wall model, so it adds the same k to each and leaves dAIC unchanged. Why these choices: docs/decisions.md.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from velab.rig import GRAVITY_M_S2, Rig
from velab.fitting.engine import gram, sumsq
from velab.fitting.solvers import levenberg_marquardt
from velab.model import ValveHeadModel
from velab.valvelaw import orifice_coupling
from velab.fitting.closure import (COUPLING, FITTED, NV, PARAM_NAMES, T50_MAX_FACTOR, closure_bounds, closure_opening,
                                   coupling_exponent, from_solver, law_words, own_valve_starts, rig_shape, to_solver)
from velab.fitting.flows import ValveInput, closure_flow, coupling_head, early_window_s


WALL = 3  # ln a, ln J'_1, ln tau_1


REFRESHES = 1  # friction-correction refreshes of the closure fit (time-domain laws only)


START_ITERATIONS = 8  # each start of the closure fit is taken this many steps before the better one goes on


# the closure fit also starts from the rig's nominal wave speed where the scanned one is further from it than this
# (in ln a): the scan lines up an elastic pipe's fronts, and creep delays them (the imperial rig: 362 for 395 m/s)
NOMINAL_START_GAP = 0.03


# the two starts of the closure: a real butterfly discharging to air, and the imposed sigmoid flow
STARTS = ((2.0, 0.05, 1.0), (1.0, 1.0, 0.0))


# the grid of characteristic powers and loss shares the Joukowsky starts are taken from
START_POWERS = (0.75, 1.5, 3.0)


START_SHARES = (0.02, 0.2, 1.0)


class _ClosureProblem:
    """Residuals of the early record against the frequency model driven by the parametric closure,
    plus a fixed time-domain correction (friction), in the variables
    x = (ln a, ln J'_1, ln tau_1, ln beta, t50, ln n, ln s, kappa, tail) (velab.fitting.manoeuvre.to_solver).

    The model is built once; a new wall changes the impedance, a new closure the flow's spectrum
    (``ValveHeadModel.flow_sums``): the Jacobian's columns are finite differences of either, in one
    batched inverse FFT."""

    STEP = 1e-6

    def __init__(self, t, d, h_meas, rig: Rig, time_model):
        self.t, self.d, self.h, self.rig, self.time_model = t, d, h_meas, rig, time_model
        self.corr = np.zeros_like(d)
        self.vm = ValveHeadModel(rig, t, band_hz=None, flow=np.zeros_like(t))
        self._cache = (None, None)

    @staticmethod
    def split(x):
        a = math.exp(x[0])
        J = np.exp(x[1:2])
        tau = np.exp(x[2:3])
        valve = from_solver(x[3 : 3 + NV])
        return a, J, tau, valve

    def flow(self, x) -> np.ndarray:
        return closure_flow(self.t, self.h, self.rig, self.split(x)[3])

    def head_fd(self, x) -> np.ndarray:
        a, J, tau, _ = self.split(x)
        return self.vm.head_of(self.vm.impedance(a, J, tau), self.vm.flow_sums(self.flow(x)))

    def residual(self, x) -> np.ndarray:
        return self.head_fd(x) + self.corr - self.d

    def jacobian(self, x) -> np.ndarray:
        a, J, tau, valve = self.split(x)
        Z0 = self.vm.impedance(a, J, tau)
        sums0 = self.vm.flow_sums(self.flow(x))
        h0 = self.vm.head_of(Z0, sums0)
        rows_z, rows_s = [], []
        for i in range(WALL):  # the wall: the impedance moves
            xp = np.array(x, dtype=float)
            xp[i] += self.STEP
            ap, Jp, taup, _ = self.split(xp)
            rows_z.append(self.vm.impedance(ap, Jp, taup))
        for i in range(WALL, WALL + NV):  # the closure: the flow moves
            if i - WALL == COUPLING:  # held at the rig's valve law (closure_bounds): a zero column, not computed
                rows_s.append(sums0)
                continue
            xp = np.array(x, dtype=float)
            xp[i] += self.STEP
            rows_s.append(self.vm.flow_sums(self.flow(xp)))
        hz = self.vm.head_of(np.array(rows_z), sums0)
        hs = self.vm.head_of(Z0, np.array(rows_s))
        return (np.vstack([hz, hs]) - h0).T / self.STEP

    def refresh(self, x) -> None:
        """The correction h_MOC - h_FD at x (the flow imposed in both)."""
        if self.time_model is None:
            return
        a, J, tau, _ = self.split(x)
        q = self.flow(x)
        t = self.t
        h_time = self.time_model.head(a, J, tau, flow=lambda s: np.interp(s, t, q))
        self.corr = h_time - self.head_fd(x)


SHAPE_PARAMS = 3  # power, loss share, tail: what holding the closure's shape at the rig's valve saves


# the gain in n ln F on the record's first part that frees the closure's shape: chi2(3)'s 1 % point (a test of
# the rig file's valve, not AIC's 2 per parameter: a shape freed by chance trades with the slow creep along the
# closure's valley; 3 of 29 records of the valve described gained 7-10 by chance, valves not the one described
# gained 114-293; docs/fitting.md, "The manoeuvre")
SHAPE_PRICE = 11.34


class EarlyPart:
    """A record's first part (``early_window_s``) as both closure fits of ``choose_closure`` take it: the
    problem (``_ClosureProblem``: the frequency model built once, the time-domain model on its grid) and the
    wave speed scanned from its fronts, set up once; t from the trigger, d the head perturbation, ``hc`` the
    coupling's head rise on the whole grid."""

    def __init__(self, t, d, rig: Rig, window_s: float, time_model=None, coupling=None):
        self.t = t = np.asarray(t, dtype=float)
        d = np.asarray(d, dtype=float)
        self.hc = hc = coupling_head(t, d, rig) if coupling is None else np.asarray(coupling, dtype=float)
        self.rig = rig
        self.ne = ne = max(16, int(np.searchsorted(t, early_window_s(rig, window_s) - 1e-9)))
        tm = None
        if time_model is not None and time_model.active:
            tm = time_model.on_grid(t[:ne])
        self.prob = _ClosureProblem(t[:ne], d[:ne], hc[:ne], rig, tm)
        self.a0 = _scan_wave_speed(self.prob, rig)

    def box(self, shape: str, kappa: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The solver's box (wall, then ``closure_bounds``). The wave speed's holds the scan's and the rig's
        nominal one: the scan assumes the valve the rig describes, and a flow that falls later than that moves it
        (when the scan took the commanded sigmoid as the flow, a quick-opening valve on the reference rig, half
        its flow at 0.30 s, not 0.17 s, pulled it to 237 m/s for 353.7; the box around it alone then held no
        closure that fits, F 90 x the noise on the first part, and the whole-window refinement started from
        nothing: tests/fitting/test_fit_manoeuvre.py, quick-opening valve)."""
        a_nom = self.rig.nominal_wave_speed_m_s
        a_lo, a_hi = min(self.a0, a_nom), max(self.a0, a_nom)
        c_lo, c_hi = closure_bounds(self.rig, shape, kappa)
        return (np.array([math.log(a_lo * 0.8), math.log(1e-6), math.log(1e-3), *c_lo]),
                np.array([math.log(a_hi * 1.25), math.log(5.0), math.log(10.0), *c_hi]))

    def wall0(self) -> list[float]:
        return [math.log(self.a0), math.log(0.05), math.log(0.05)]


def fit_closure(t, d, rig: Rig, window_s: float, time_model=None, coupling=None,
                shape: str = "fitted") -> ValveInput:
    """The parametric closure fitted on the record's first part (``early_window_s``): t from the
    trigger (starting at 0), d the head perturbation (also the measured head rise of the coupling),
    ``time_model`` a velab.fitting.friction.TimeDomainModel on the same grid (None: the frequency
    model is the rig's model). Returns the flow on the whole grid."""
    return fit_early(EarlyPart(t, d, rig, window_s, time_model, coupling), shape)[0]


def fit_early(early: EarlyPart, shape: str, extra_starts=(), kappa: float | None = None) -> tuple[ValveInput, np.ndarray]:
    """``fit_closure`` on a set-up first part; also the solver's optimum. ``extra_starts``: solver points
    (clipped to the box) tried besides the Joukowsky and own-valve starts. Held at the rig's shape, the
    Joukowsky start is the rig's (power, loss share) alone: the grid's others, clipped to it, only repeat it.
    ``kappa``: the coupling exponent held (None: the rig's valve law's, ``coupling_exponent``)."""
    prob, rig, t = early.prob, early.rig, early.t
    m = rig.manoeuvre
    lo, hi = early.box(shape, kappa)
    wall0 = early.wall0()
    # the starts are taken a few steps (the friction correction at the rig's sigmoid), the best one is solved
    # to the end with the correction refreshed at its optimum
    prob.refresh(np.clip(np.array(wall0 + to_solver((m.beta_per_s, m.half_closure_s, 1.0, 1.0, 0.0, 0.0))), lo, hi))
    shapes = [rig_shape(rig)[:2]] if shape == "rig" else None
    closures = joukowsky_starts(prob.t, prob.d, prob.h, rig, early.a0, shapes=shapes, kappa=kappa) + own_valve_starts(rig)
    starts = [np.clip(np.array(wall0 + to_solver(v)), lo, hi) for v in closures]
    a_nom = rig.nominal_wave_speed_m_s
    if abs(math.log(a_nom / early.a0)) > NOMINAL_START_GAP:  # the scan far from the rig's wave speed: both
        starts.append(np.clip(np.array([math.log(a_nom), *wall0[1:]] + to_solver(closures[0])), lo, hi))
    starts += [np.clip(np.asarray(x, dtype=float), lo, hi) for x in extra_starts]
    tries = [levenberg_marquardt(prob.residual, prob.jacobian, x, lo, hi, max_iter=START_ITERATIONS) for x in starts]
    tries.sort(key=lambda s: sumsq(s.fun))
    sol = tries[0]
    other = [s for s in tries[1:] if np.max(np.abs(s.x[WALL:] - sol.x[WALL:])) > 0.05]
    alternatives = tuple(dict(zip(PARAM_NAMES, (float(v) for v in prob.split(s.x)[3]))) for s in other[:1])
    for it in range(1 + (REFRESHES if prob.time_model is not None else 0)):
        if it:
            prob.refresh(sol.x)
        sol = levenberg_marquardt(prob.residual, prob.jacobian, sol.x, lo, hi)
    F = float(np.mean(sol.fun ** 2))
    x = sol.x
    _, _, _, valve = prob.split(x)
    se = closure_standard_errors(sol, F, prob.d.size)
    params = dict(zip(PARAM_NAMES, (float(v) for v in valve)))
    # standard errors in the reported units (the solver's variables are logs for beta, n, s)
    ses = {}
    for i, name in enumerate(PARAM_NAMES):
        s = se[WALL + i]
        ses[name] = float(s * params[name]) if name in ("beta_per_s", "power", "loss_share") else float(s)
    q = closure_flow(t, early.hc, rig, valve)
    ne = early.ne
    text = (f"flow at the valve from a fitted closure (no valve position in the record): effective opening "
            f"T(sigmoid(beta (t - t_half))) with beta = {params['beta_per_s']:.4g} 1/s, t_half = "
            f"{params['t_half_s'] * 1e3:.4g} ms, characteristic power {params['power']:.3g}, valve loss share "
            f"{params['loss_share']:.3g}, orifice coupling {params['coupling']:.3g} ({law_words(rig, params['coupling'])}), "
            f"fitted on the first {t[ne - 1] + t[1] - t[0]:.3g} s")
    held = SHAPE_PARAMS if shape == "rig" else 0
    return ValveInput("fitted", q, params, ses, text, k=FITTED - held, alternatives=alternatives, shape=shape,
                      early_F=F, early_n=int(prob.d.size)), x


def shape_score(early: EarlyPart, x) -> float:
    """The gain in n ln F that freeing the closure's shape predicts at ``x``, the held fit's optimum (a score
    test): the Gauss-Newton step over the free box's variables against the step over the held box's, both from
    x on its residual and Jacobian (the held fit's correction). A variable on a bound that the step would take
    out of the box is held there (the tail of a power-law valve, at 0, cannot go negative). inf where no
    prediction can be made (the free fit is then made)."""
    prob = early.prob
    r = prob.residual(x)
    J = prob.jacobian(x)
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(J))):
        return math.inf
    rss = [0.0, 0.0]
    for k, shape in enumerate(("rig", "fitted")):
        lo, hi = early.box(shape)
        active = lo < hi
        for _ in range(active.size):
            cols = np.flatnonzero(active)
            Ja = J[:, cols]
            scale = np.sqrt(np.maximum(np.einsum("ij,ij->j", Ja, Ja), 1e-300))
            try:
                step = np.linalg.lstsq(Ja / scale, -r, rcond=None)[0] / scale
            except np.linalg.LinAlgError:  # (no prediction: the free fit decides)
                return math.inf
            out = ((x[cols] <= lo[cols] + 1e-12) & (step < 0)) | ((x[cols] >= hi[cols] - 1e-12) & (step > 0))
            if not out.any():
                break
            active[cols[out]] = False
        rss[k] = sumsq(r + Ja @ step)
    held_rss, free_rss = rss
    if free_rss <= 0.0:
        return math.inf
    return float(prob.d.size * math.log(max(held_rss, free_rss) / free_rss))


def choose_closure(t, d, rig: Rig, window_s: float, time_model=None, coupling=None) -> ValveInput:
    """The closure fitted on the record's first part with its shape held at the valve the rig file describes
    (``rig_shape``, only the timing fitted), and with its shape free where freeing it may pay: the rig's shape
    is kept unless the free one gains more than SHAPE_PRICE in n ln F there. The free fit is made only where
    the held fit's score (``shape_score``: the gain a Gauss-Newton step predicts) is above that price (the two
    agree within a few units where the valve is the one described); otherwise the held closure is kept with the
    prediction as its ``shape_gain``. Over a campaign's whole windows the free shape's power,
    loss share and actuator rate trade with the slow creep along a curved valley that the linearised band does
    not cover (docs/fitting.md, "The manoeuvre" and "Joint fits"); a valve that is not the one described shows
    itself as a large gain."""
    early = EarlyPart(t, d, rig, window_s, time_model, coupling)
    held, x_held = fit_early(early, "rig")
    price = SHAPE_PRICE
    power, share, tail = rig_shape(rig)
    kept = (f"{held.text}; its shape held at the rig's valve (power {power:g}, loss share {share:g}"
            f"{', its table' if tail else ''}): ")
    score = shape_score(early, x_held)
    if score <= price:
        return replace(held, alternatives=(), shape_gain=score,
                       text=f"{kept}a fitted shape is predicted to gain {score:.1f} in n ln F (its score at the "
                            f"held closure), not more than {price:g} (chi2(3)'s 1 % point)")
    # (the held optimum is one of the free fit's starts: the free family contains it, so it cannot end worse)
    free, _ = fit_early(early, "fitted", extra_starts=(x_held,))
    gain = free.early_n * math.log(held.early_F / free.early_F) if free.early_F > 0 else math.inf
    if gain > price:
        free = replace(free, shape_gain=gain, text=f"{free.text}; its shape fitted (it gains {gain:.1f} in n ln F "
                                                   f"over the rig's valve's, more than {price:g}, chi2(3)'s 1 % point)")
        return other_law(early, free)
    return replace(held, alternatives=(), shape_gain=gain,
                   text=f"{kept}a fitted shape gained {gain:.1f} in n ln F, not more than {price:g} (chi2(3)'s 1 % "
                        f"point)")


# the valve the rig file describes is not the record's (its shape rejected, ``choose_closure``): its valve law (the
# orifice coupling or the flow imposed as such) is in question too, and the closure is fitted again under the other
# law; taken if it gains more than this in n ln F on the record's first part (one discrete choice: chi2(1)'s 1 % point)
OTHER_LAW_PRICE = 6.63


def other_law(early: EarlyPart, free: ValveInput) -> ValveInput:
    """``free`` (the closure with its shape fitted, the rig's valve rejected), or the closure fitted under the other
    valve law (the coupling exponent 1 - the rig's: an imposed flow for an orifice rig, and the reverse) where that
    fits the first part better by more than OTHER_LAW_PRICE. Why: the family with the rig's orifice coupling cannot
    hold a flow imposed as such (Q = Q0 phi(x) c(t) with c = sqrt((Hv0 + h)/Hv0) up to 1.23 on the reference rig),
    and what it left was taken up by the wave speed and a fast element (docs/fitting.md, "A valve its rig file does
    not describe")."""
    kappa = 1.0 - coupling_exponent(early.rig)
    alt, _ = fit_early(early, "fitted", kappa=kappa)
    gain = free.early_n * math.log(free.early_F / alt.early_F) if alt.early_F > 0 else math.inf
    if gain > OTHER_LAW_PRICE:
        return replace(alt, shape_gain=free.shape_gain,
                       text=f"{alt.text}; its shape fitted (the rig's valve's gained {free.shape_gain:.1f} less in "
                            f"n ln F), and the coupling of the other valve law (it gains {gain:.1f} in n ln F over "
                            f"the rig's law's, more than {OTHER_LAW_PRICE:g})")
    return replace(free, text=f"{free.text}; the other valve law gained {gain:.1f} in n ln F, not more than "
                              f"{OTHER_LAW_PRICE:g}")


def joukowsky_starts(t, d, hc, rig: Rig, a: float, keep: int = 3, shapes=None, kappa: float | None = None) -> list[tuple]:
    """Starts for the closure: before the first reflection returns (2L/a) the head at the valve is
    the Joukowsky head of the flow change, so 1 - h / (B Q0), B = a/(gA), is the flow ratio (creep
    lowers it a little). Every (power, loss share) of a small grid gets its (beta, t_half) fitted to
    that curve (the coupling the rig's); the ``keep`` best (beta, t_half, power, share, coupling, tail)
    are returned. ``shapes``: the (power, loss share) pairs tried instead of the grid's; ``kappa``: the coupling
    exponent (None: the rig's)."""
    t = np.asarray(t, dtype=float)
    kappa = coupling_exponent(rig) if kappa is None else float(kappa)
    n = int(np.searchsorted(t, 0.95 * 2.0 * rig.pipe.length_m / a))
    pairs = [(p, s) for p, s, _ in STARTS] if shapes is None else list(shapes)
    if n < 8:
        return [(rig.manoeuvre.beta_per_s, rig.manoeuvre.half_closure_s, p, s, kappa, 0.0) for p, s in pairs]
    B = a / (GRAVITY_M_S2 * rig.pipe.area_m2)
    q0 = rig.steady_flow_m3_s
    tt, r_obs, c = t[:n], 1.0 - np.asarray(d[:n]) / (B * q0), orifice_coupling(hc[:n], rig.valve_head_m)
    below = np.flatnonzero(r_obs < 0.5)
    t50 = float(tt[below[0]]) if below.size else rig.manoeuvre.half_closure_s
    beta0 = rig.manoeuvre.beta_per_s
    found = []
    ck = c ** kappa
    grid = [(p, s) for p in START_POWERS for s in START_SHARES] if shapes is None else list(shapes)
    for power, share in grid:

        def res(x, power=power, share=share):
            b, th, *_ = from_solver([x[0], x[1], math.log(power), math.log(share), 0.0, 0.0])
            return closure_opening(tt, b, th, power, share) * ck - r_obs

        def jac(x, res=res):
            r0 = res(x)
            cols = []
            for i in range(2):
                xp = np.array(x, dtype=float)
                xp[i] += 1e-6
                cols.append((res(xp) - r0) / 1e-6)
            return np.array(cols).T

        lo2 = np.array([math.log(beta0 / 5), 0.0])
        hi2 = np.array([math.log(beta0 * 5), T50_MAX_FACTOR * rig.manoeuvre.half_closure_s + 1.0])
        sol = levenberg_marquardt(res, jac, np.clip([math.log(beta0), t50], lo2, hi2), lo2, hi2, max_iter=15)
        v = from_solver([sol.x[0], sol.x[1], math.log(power), math.log(share), kappa, 0.0])
        found.append((sumsq(sol.fun), v))
    found.sort(key=lambda f: f[0])
    return [v for _, v in found[:keep]]


def closure_standard_errors(sol, F: float, n: int) -> np.ndarray:
    J = sol.jac
    try:
        cov = np.linalg.pinv(gram(np.ascontiguousarray(J.T))) * F * n / max(n - J.shape[1], 1)
    except np.linalg.LinAlgError:
        return np.full(J.shape[1], math.nan)
    return np.sqrt(np.maximum(np.diag(cov), 0.0))


def _scan_wave_speed(prob: _ClosureProblem, rig: Rig) -> float:
    """Elastic pipe driven by the rig's own valve (``rig_shape``) on its commanded sigmoid, coupled to the measured
    head: the wave speed that best lines up the early fronts (a start for the closure fit: the fronts' timing sets
    it). The sigmoid imposed as the flow instead (the paper's model) closes earlier than a butterfly valve passes
    its flow, and the scan made up for it: on the imperial rig at 1.25 x its Q0, 359.5 m/s for 395, where the
    closure fit with the rig's shape then stopped (F 18 x the noise's on the first part)."""
    a_nom = rig.nominal_wave_speed_m_s
    power, share, tail = rig_shape(rig)
    q = closure_flow(prob.t, prob.h, rig, (rig.manoeuvre.beta_per_s, rig.manoeuvre.half_closure_s, power, share,
                                           coupling_exponent(rig), tail))
    vm, sums, none = prob.vm, prob.vm.flow_sums(q), np.zeros(0)

    def F(a):
        return float(np.mean((vm.head_of(vm.impedance(a, none, none), sums) - prob.d) ** 2))

    grid = np.geomspace(a_nom / 2, a_nom * 2, 241)
    i = int(np.argmin([F(a) for a in grid]))
    fine = np.geomspace(grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)], 41)
    return float(fine[int(np.argmin([F(a) for a in fine]))])
