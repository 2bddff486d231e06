"""The manoeuvre in the fit: the flow at the valve that drives the model, built from the record.

The frequency-domain model (velab.model) takes the flow at the valve q(t) = Q(t) - Q0 as its input.
A real valve does not impose the paper's sigmoid: the actuator moves the valve in *position* and the
flow obeys the orifice law through the valve pair (physics.md section 10, velab.valvelaw):

    Q(t) = Q0 tau(t) sqrt((Hv0 + h(t)) / Hv0)

The head rise h is the *measured* one (the record holds it), so the input stays linear for the
model. Two ways to the effective opening tau(t), named in the result (``ValveInput.source``):

* ``"position"``: the record holds the valve position and the rig describes the valve
  (characteristic, loss share, law): tau(t) = rig.valve.opening(p_measured(t)). A rig whose valve law
  is ``"imposed"`` (the paper's model, and every run made before the valve law existed) gives
  Q = Q0 p/100 instead;
* ``"fitted"``: no position record (imported CSVs) -- the effective opening is a parametric monotone
  closure fitted as nuisance parameters, the same for every wall model (so they add the same k to
  each and leave dAIC unchanged):

      Q / Q0 = T(sigmoid(beta (t - t_half))) * c(t)^kappa,   T(x) = 1 / sqrt((1 - s) + s x^(-2 n)),
      c(t) = sqrt((Hv0 + h_measured(t)) / Hv0)

  beta, t_half: the actuator's sigmoid in position; n: the characteristic's power (phi = x^n);
  s: the valve's share of the steady loss; kappa: how much of the orifice coupling acts, which the
  rig's valve law states and is not fitted (``coupling_exponent``: 1 for the orifice law, a valve
  pair discharging to air; 0 for a flow imposed as such). The family holds a real butterfly
  (n = 2, s = 0.05, kappa = 1) and the paper's imposed sigmoid flow exactly (n = 1, s = 1,
  kappa = 0). Fitted, kappa was 0.07-0.27 for 1 on a campaign's head-only runs: it trades with the
  characteristic and the fast creep element, and its regressor, the measured head, carries the
  record's own noise (a model error of 4.5 mm rms that correlates with the noise, 16 in n ln F per
  8 s run at sigma 0.1 m), which pulls it toward 0; the fast element took the difference (a joint
  fit's J(0.05 s) 0.3-0.9 % high, outside its band in 3 campaigns of 8).

  The closure is fitted on the record's first part (the closure and the first wave periods, which
  it shapes) jointly with an S2 wall (which stands in for whatever wall the sweep then finds:
  the closure's parameters barely depend on it), through the same friction correction as the
  sweep (the time-domain model at the current parameters, velab.fitting.friction).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import lru_cache

import numpy as np

from velab.rig import GRAVITY_M_S2, Rig
from scipy.signal import butter, sosfiltfilt

from velab.errors import DataError
from velab.fitting.engine import gram, sumsq
from velab.fitting.solvers import levenberg_marquardt
from velab.fitting.friction import TimeDomainModel
from velab.model import ValveHeadModel, flow_perturbation, manoeuvre_band_hz
from velab.valvelaw import commanded_position_pct, orifice_coupling

# the closure is fitted before the first reflection returns to the valve (2L/a), or over 1.5 x its
# commanded span if that is longer: there the head is the pipe's characteristic impedance times the
# flow, and the wall acts only through its fastest creep (one Kelvin-Voigt element stands in for it)
CLOSURE_SPAN_FACTOR = 1.5
WALL = 3  # ln a, ln J'_1, ln tau_1
COUPLING_SPAN_FACTOR = 3.0  # the coupling's head is filtered over this multiple of the closure's window
COUPLING_BAND_FACTOR = 2.0  # the coupling's head is low-passed at this multiple of the manoeuvre's band
REFRESHES = 1  # friction-correction refreshes of the closure fit (time-domain laws only)
START_ITERATIONS = 8  # each start of the closure fit is taken this many steps before the better one goes on
# the closure fit also starts from the rig's nominal wave speed where the scanned one is further from it than this
# (in ln a): the scan lines up an elastic pipe's fronts, and creep delays them (the imperial rig: 362 for 395 m/s)
NOMINAL_START_GAP = 0.03
PARAM_NAMES = ("beta_per_s", "t_half_s", "power", "loss_share", "coupling", "tail")
NV = len(PARAM_NAMES)
COUPLING = PARAM_NAMES.index("coupling")
FITTED = NV - 1  # the closure's fitted parameters: all but the coupling, which the rig's valve law states
# the two starts of the closure: a real butterfly discharging to air, and the imposed sigmoid flow
STARTS = ((2.0, 0.05, 1.0), (1.0, 1.0, 0.0))
# the grid of characteristic powers and loss shares the Joukowsky starts are taken from
START_POWERS = (0.75, 1.5, 3.0)
START_SHARES = (0.02, 0.2, 1.0)
T50_MAX_FACTOR = 4.0  # the flow's half-closure instant is sought up to this multiple of the commanded one (+ 1 s)


@dataclass(frozen=True)
class ValveInput:
    """The flow at the valve that drives the model, on the fit's grid, and how it was obtained."""

    source: str  # "position" | "fitted" | "rig" (the rig's sigmoid: no record of the head to couple)
    flow: np.ndarray  # q(t) = Q(t) - Q0 on the record's grid (0 before the trigger), m^3/s
    params: dict = field(default_factory=dict)  # the fitted closure's parameters
    se: dict = field(default_factory=dict)  # and their standard errors
    text: str = ""
    k: int = 0  # nuisance parameters fitted (added to every model's count)
    gain: float = math.nan  # n ln(F before / F after) of its refinement on the whole window (refine_closure)
    # other closures of the first part (the first part does not tell them apart): the whole-window refinement
    # also starts from them
    alternatives: tuple = ()
    refined_with: str = ""  # the model whose wall the closure was refined with (velab.fitting.refine), if it was
    # the calibrated model whose head the orifice coupling takes (``closure_coupling``): {"wave_speed_m_s", "J_rel",
    # "tau_s", "closure": {PARAM_NAMES: value}}; {} for the measured head
    coupling: dict = field(default_factory=dict)
    # "fitted": the closure's shape (power, loss share, tail) fitted; "rig": held at the valve the rig file
    # describes (``rig_shape``), only its timing fitted (``choose_closure``)
    shape: str = "fitted"
    early_F: float = math.nan  # the closure fit's mean squared residual on the record's first part, and its samples
    early_n: int = 0
    shape_gain: float = math.nan  # n ln F the free shape gained over the rig's on the first part (choose_closure)

    def describe(self) -> dict:
        out = {"source": self.source, "params": dict(self.params), "se": dict(self.se), "text": self.text,
               "nuisance_parameters": self.k}
        if self.source == "fitted":
            out["shape"] = self.shape
            if math.isfinite(self.shape_gain):
                out["shape_gain"] = self.shape_gain
        if self.refined_with:
            out["refined_with"] = self.refined_with
        if self.coupling:
            out["coupling_head"] = {k: (dict(v) if isinstance(v, dict) else v) for k, v in self.coupling.items()}
        return out


def sigmoid(u) -> np.ndarray:
    return 0.5 * (1.0 - np.tanh(0.5 * np.asarray(u, dtype=float)))  # 1 / (1 + exp(u)), no overflow


def characteristic(x, power: float, tail: float = 0.0, shape=None) -> np.ndarray:
    """phi(x) = (1 - w) x^n + w g(x): a power law blended with ``shape`` g (``tail`` w): g(x) = x by default
    (a manufacturer's table is often linear near shut where a power law is not), the rig's own table where
    it has one (``tail_shape``)."""
    x = np.asarray(x, dtype=float)
    with np.errstate(divide="ignore", over="ignore", under="ignore", invalid="ignore"):
        xn = np.where(x > 0, np.exp(power * np.log(np.where(x > 0, x, 1.0))), 0.0)
    if not tail:
        return xn
    return (1.0 - tail) * xn + tail * (x if shape is None else shape(x))


def tail_shape(rig: Rig):
    """The closure's blended shape g (``characteristic``): the rig's characteristic when it is a table (a
    function of x = p/100; the family then holds the rig's valve exactly at w = 1), else None (linear)."""
    valve = getattr(rig, "valve", None)
    if valve is None or valve.characteristic != "table":
        return None
    return _table_shape(tuple(valve.position_pct), tuple(valve.flow_ratio))


@lru_cache(maxsize=8)
def _table_shape(position_pct: tuple, flow_ratio: tuple):
    from scipy.interpolate import PchipInterpolator  # monotone, no overshoot: as Valve.flow_ratio_at

    f = PchipInterpolator(np.asarray(position_pct) / 100.0, np.asarray(flow_ratio))
    return lambda x: np.clip(f(np.clip(np.asarray(x, dtype=float), 0.0, 1.0)), 0.0, 1.0)


def own_valve_starts(rig: Rig) -> list[tuple]:
    """[the closure (``PARAM_NAMES``) of the rig's own valve on its commanded sigmoid] for a rig whose
    characteristic is a table (w = 1 on ``tail_shape``, its loss share; the imposed sigmoid if its law says so),
    [] otherwise: the power-law starts hold a power law's basin already (added for every rig, this start took a
    campaign's joint J(0.5 s) from the truth to 2.6 of its standard errors)."""
    if tail_shape(rig) is None:
        return []
    m = rig.manoeuvre
    power, share, tail = rig_shape(rig)
    return [(m.beta_per_s, m.half_closure_s, power, share, coupling_exponent(rig), tail)]


def closure_opening(t, beta: float, t_half: float, power: float, share: float, tail: float = 0.0,
                    shape=None) -> np.ndarray:
    """T(sigmoid(beta (t - t_half))) for t >= 0, 1 before the trigger; T(x) = 1/sqrt((1-s) + s/phi(x)^2)."""
    t = np.asarray(t, dtype=float)
    phi = characteristic(sigmoid(beta * (t - t_half)), power, tail, shape)
    with np.errstate(divide="ignore", over="ignore", under="ignore"):
        inv = np.where(phi > 0, 1.0 / np.where(phi > 0, phi, 1.0) ** 2, np.inf)
        tau = np.where(phi > 0, 1.0 / np.sqrt((1.0 - share) + share * inv), 0.0)
    return np.where(t >= 0, tau, 1.0)


def coupling_head(t, h, rig: Rig) -> np.ndarray:
    """The measured head rise as the orifice coupling takes it: low-passed (zero phase) at twice the
    manoeuvre's band, so that the transducer's noise does not enter the flow (the head rise of a
    closure is slower than that)."""
    t = np.asarray(t, dtype=float)
    h = np.asarray(h, dtype=float)
    if t.size < 32:
        return h
    fs = 1.0 / float(t[1] - t[0])
    fc = COUPLING_BAND_FACTOR * manoeuvre_band_hz(rig)
    if fc >= 0.45 * fs:
        return h
    sos = butter(4, fc, fs=fs, output="sos")
    return sosfiltfilt(sos, h)


def half_flow_offset(power: float, share: float, tail: float = 0.0) -> float:
    """u50 with T(sigmoid(u50)) = 1/2: the flow is half closed at t50 = t_half + u50 / beta (with the linear
    tail; with a table's (``tail_shape``) t50 stays this coordinate, near the half-flow instant)."""
    return _half_flow_offset(float(power), float(share), float(tail))


@lru_cache(maxsize=4096)  # a pure function the solvers ask again at every point they revisit (from_solver)
def _half_flow_offset(power: float, share: float, tail: float) -> float:
    phi50 = math.sqrt(share / (3.0 + share))
    x50 = phi50 ** (1.0 / power)
    if tail > 0.0:  # (1 - w) x^n + w x = phi50: phi is increasing and convex or concave, Newton from x^n's root
        lo, hi = 0.0, 1.0
        for _ in range(40):
            f = (1.0 - tail) * x50**power + tail * x50 - phi50
            if f > 0:
                hi = x50
            else:
                lo = x50
            df = (1.0 - tail) * power * x50 ** (power - 1.0) + tail
            x_new = x50 - f / df if df > 0 else 0.5 * (lo + hi)
            if not lo < x_new < hi:  # (a Newton step out of the bracket: bisect)
                x_new = 0.5 * (lo + hi)
            if abs(x_new - x50) < 1e-15:
                break
            x50 = x_new
    return math.log(1.0 / x50 - 1.0)


def to_solver(valve) -> list[float]:
    """(beta, t_half, n, s, kappa) -> the solver's (ln beta, t50, ln n, ln s, kappa). The flow's own
    half-closure instant t50 is what the record shows (the Joukowsky head's half-way point); with it
    as a variable instead of the position's t_half, the shape (n, s) no longer drags the timing."""
    beta, t_half, power, share, kappa, tail = valve
    return [math.log(beta), t_half + half_flow_offset(power, share, tail) / beta, math.log(power), math.log(share),
            kappa, tail]


def from_solver(v) -> tuple:
    """Inverse of :func:`to_solver`."""
    beta, power, share = math.exp(v[0]), math.exp(v[2]), math.exp(v[3])
    return beta, v[1] - half_flow_offset(power, share, v[5]) / beta, power, share, v[4], v[5]


def closure_flow(t, h, rig: Rig, params) -> np.ndarray:
    """q(t) of the parametric closure (``PARAM_NAMES`` order) with the head rise h (``coupling_head``)."""
    beta, t_half, power, share, kappa, tail = params
    c = orifice_coupling(h, rig.valve_head_m)
    with np.errstate(divide="ignore"):
        ck = np.where(c > 0, c ** kappa, 0.0 if kappa > 0 else 1.0)
    q = rig.steady_flow_m3_s * (closure_opening(t, beta, t_half, power, share, tail, tail_shape(rig)) * ck - 1.0)
    return np.where(np.asarray(t) >= 0, q, 0.0)


def position_flow(t, h, position_pct, rig: Rig) -> np.ndarray:
    """q(t) from the recorded valve position through the rig's valve (law, characteristic, share)."""
    t = np.asarray(t, dtype=float)
    p = np.clip(np.asarray(position_pct, dtype=float), 0.0, 100.0)
    q0 = rig.steady_flow_m3_s
    if rig.valve.law == "imposed":
        q = q0 * (p / 100.0 - 1.0)
    else:
        q = q0 * (rig.valve.opening(p) * orifice_coupling(h, rig.valve_head_m) - 1.0)
    return np.where(t >= 0, q, 0.0)


def closing_position(t, position_pct, rig: Rig) -> np.ndarray:
    """The recorded position as the valve's stroke: low-passed like the coupling's head, then its
    running minimum after the trigger (a closure only closes). Near shut a steep characteristic turns
    the feedback's noise into flow (a quick-opening valve passes 6 % of Q0 at 0.02 % open with a 5 %
    loss share); the running minimum reaches the shut valve and stays there."""
    t = np.asarray(t, dtype=float)
    p = coupling_head(t, np.asarray(position_pct, dtype=float), rig)
    after = t >= 0
    p[after] = np.minimum.accumulate(p[after])
    return np.clip(p, 0.0, 100.0)


def from_position(t, h, position_pct, rig: Rig) -> ValveInput:
    position_pct = closing_position(t, position_pct, rig)
    v = rig.valve
    text = ("flow at the valve from the recorded valve position: "
            + ("Q0 p/100 (the rig's imposed-flow valve)" if v.law == "imposed" else
               f"{v.describe()}, orifice coupling from the measured head"))
    return ValveInput("position", position_flow(t, h, position_pct, rig), text=text)


def early_window_s(rig: Rig, window_s: float) -> float:
    """Up to the first reflection's return, 2L/a, or 1.5 x the commanded closure (down to 0.1 %)."""
    closure = rig.manoeuvre.closed_s
    return min(window_s, max(2.0 * rig.pipe.length_m / rig.nominal_wave_speed_m_s, CLOSURE_SPAN_FACTOR * closure))


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


def coupling_exponent(rig: Rig) -> float:
    """The fitted closure's kappa, as the rig's valve law states it: 1 for the orifice law (the head rise
    acts on the flow through sqrt((Hv0 + h)/Hv0)), 0 for a flow imposed as such."""
    return 0.0 if rig.valve.law == "imposed" else 1.0


def law_words(rig: Rig, kappa: float) -> str:
    """How a fitted closure's coupling exponent came about, for its text."""
    if kappa == coupling_exponent(rig):
        return "the rig's valve law"
    return ("the flow imposed as such, not the rig's orifice law" if kappa == 0.0 else
            "the orifice law, not the rig's imposed flow") + ": the record's first part shows it"


def closure_kappa(rig: Rig, closure=None) -> float:
    """The coupling exponent a fitted closure holds: ``closure``'s (a ValveInput or its params dict) where it
    has one (``choose_closure`` may have taken the other valve law, ``OTHER_LAW_PRICE``), else the rig's
    (``coupling_exponent``)."""
    params = getattr(closure, "params", closure) or {}
    kappa = params.get("coupling") if isinstance(params, dict) else None
    return coupling_exponent(rig) if kappa is None or not math.isfinite(float(kappa)) else float(kappa)


def closure_bounds(rig: Rig, shape: str = "fitted", kappa: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The box of the closure's solver variables (``to_solver``: ln beta, t_half, ln power, ln loss
    share, coupling, tail): beta within 5x the commanded one, the flow's half-closure instant up to
    T50_MAX_FACTOR x the commanded one (+ 1 s), power 0.3-6, loss share 0.001-1; the coupling held at
    the rig's (``coupling_exponent``: its bounds coincide, so the solvers hold it; ``kappa``: held there instead,
    ``closure_kappa``). ``shape`` "rig": power, loss share and tail held at the rig's valve too (``rig_shape``)."""
    m = rig.manoeuvre
    kappa = coupling_exponent(rig) if kappa is None else float(kappa)
    lo = np.array([math.log(m.beta_per_s / 5), 0.0, math.log(0.3), math.log(1e-3), kappa, 0.0])
    hi = np.array([math.log(m.beta_per_s * 5), T50_MAX_FACTOR * m.half_closure_s + 1.0, math.log(6.0), 0.0, kappa, 1.0])
    if shape == "rig":
        power, share, tail = rig_shape(rig)
        for i, v in ((2, math.log(power)), (3, math.log(share)), (5, tail)):
            lo[i] = hi[i] = v
    return lo, hi


SHAPE_PARAMS = 3  # power, loss share, tail: what holding the closure's shape at the rig's valve saves
# the gain in n ln F on the record's first part that frees the closure's shape: chi2(3)'s 1 % point (a test of
# the rig file's valve, not AIC's 2 per parameter: a shape freed by chance trades with the slow creep along the
# closure's valley; 3 of 29 records of the valve described gained 7-10 by chance, valves not the one described
# gained 114-293; docs/fitting.md, "The manoeuvre")
SHAPE_PRICE = 11.34
# a head-only record's closure (every fit path: single, sections, joint): the shape of the valve its rig file
# describes unless the record's first part shows another (choose_closure)
CLOSURE_SHAPE = "auto"


def rig_shape(rig: Rig) -> tuple[float, float, float]:
    """(power, loss share, tail) of the closure family that is the rig's own valve (``closure_opening``): its
    characteristic's power (a table: w = 1 on ``tail_shape``) and loss share; the imposed flow: n = 1, s = 1."""
    valve = rig.valve
    if valve.law == "imposed":
        return 1.0, 1.0, 0.0
    if valve.characteristic == "table":
        return 2.0, float(valve.series_loss_share), 1.0
    return float(valve.power), float(valve.series_loss_share), 0.0


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
    se = _standard_errors(sol, F, prob.d.size)
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


def _standard_errors(sol, F: float, n: int) -> np.ndarray:
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


def tm_flow(t, q):
    """The flow on the grid as the time-domain model takes it (t -> q, linear between samples)."""
    return lambda s: np.interp(s, t, q)


def coupling_model(a: float, J_rel, tau, closure) -> dict:
    """``ValveInput.coupling``: the model (wall, closure's parameters in PARAM_NAMES order) whose head the orifice
    coupling takes (``closure_coupling``)."""
    return {"wave_speed_m_s": float(a), "J_rel": [float(v) for v in J_rel], "tau_s": [float(v) for v in tau],
            "closure": dict(zip(PARAM_NAMES, (float(v) for v in closure)))}


def closure_coupling(t, d, rig: Rig, model: dict | None, measured=None) -> np.ndarray:
    """The head rise a fitted closure's orifice coupling takes, on t (from the trigger): the head of ``model``
    (``ValveInput.coupling``: a calibrated wall and the closure, the time-domain model with a nonlinear
    friction, its flow built on the measured coupling head) over the coupling's span, where the valve closes;
    the measured head low-passed (``_coupling``; ``measured`` if already computed) without a model and after
    the span (the valve shut, the coupling idle).

    The measured head carries the record's noise into the flow (a model error of 4.5 mm rms on material A at
    sigma 0.1 m, 16 in n ln F per 8 s run, correlated with the noise): the fit's parameters took it up (the
    fitted coupling exponent was pulled toward 0 and the fast element with it; held at the rig's 1, a
    quick-opening valve's wave speed came out 0.36-0.39 m/s high for standard errors of 0.07). The head of
    the calibrated model has no noise (velab.fitting.refine sets it)."""
    t = np.asarray(t, dtype=float)
    hc = _coupling(t, np.asarray(d, dtype=float), rig) if measured is None else np.array(measured, dtype=float)
    if not model:
        return hc
    ne = min(t.size, max(16, int(np.searchsorted(t, COUPLING_SPAN_FACTOR * early_window_s(rig, math.inf)))))
    te = t[:ne]
    q = closure_flow(te, hc[:ne], rig, [float(model["closure"].get(k, 0.0)) for k in PARAM_NAMES])
    a, J, tau = model["wave_speed_m_s"], np.asarray(model["J_rel"], dtype=float), np.asarray(model["tau_s"], dtype=float)
    tm = TimeDomainModel(rig, te)
    if tm.active:
        hc[:ne] = tm.head(a, J, tau, flow=tm_flow(te, q))
    else:
        vm = ValveHeadModel(rig, te, band_hz=None, flow=q)
        hc[:ne] = vm.head_of(vm.impedance(a, J, tau), vm.flow_sums(q))
    return hc


def _coupling(t: np.ndarray, d: np.ndarray, rig: Rig) -> np.ndarray:
    """The head rise the orifice coupling takes: ``coupling_head`` over a span that does not depend on
    the window's length (a lead fit and the final fit of one record see the same closure); after it
    the valve is shut and the coupling idle."""
    span = int(np.searchsorted(t, COUPLING_SPAN_FACTOR * early_window_s(rig, math.inf)))
    hc = np.asarray(d, dtype=float).copy()
    hc[:span] = coupling_head(t[:span], hc[:span], rig)
    return hc


MODES = ("auto", "fitted", "rig")


def valve_input(t, d, rig: Rig, window_s: float, *, position_pct=None, mode: str = "auto",
                closure: ValveInput | dict | None = None, shape: str = "fitted") -> ValveInput:
    """The flow at the valve for a prepared record (t from the trigger, d the head perturbation):
    ``mode`` "auto" -- from the recorded position if there is one, else the fitted closure;
    "fitted" -- the fitted closure even with a position record; "rig" -- the rig's commanded sigmoid
    imposed as the flow (the paper's model: no coupling, nothing fitted). ``closure``: a closure
    already fitted on this record's first part (a lead fit's ``settings["manoeuvre"]``): its
    parameters drive this window too, and the closure is not fitted again. ``shape``: "fitted" (the closure's
    shape fitted), "auto" (``choose_closure``: the rig's valve's shape unless the record shows another)."""
    if mode not in MODES:
        raise DataError(f"unknown manoeuvre input {mode!r} (choose from {', '.join(MODES)})")
    t = np.asarray(t, dtype=float)
    if mode == "rig":
        return ValveInput("rig", flow_perturbation(t, rig),
                          text="flow at the valve imposed as the rig's sigmoid Q0 / (1 + exp(beta t + gamma)) "
                               "(the paper's model: no valve law)")
    hc = _coupling(t, d, rig)
    if position_pct is not None and mode == "auto":
        return from_position(t, hc, position_pct, rig)
    old = closure.describe() if isinstance(closure, ValveInput) else closure
    if old and old.get("source") == "fitted":
        params = {k: float(old["params"].get(k, 0.0)) for k in PARAM_NAMES}
        coupling = dict(old.get("coupling_head") or {})
        hc = closure_coupling(t, d, rig, coupling, measured=hc)
        return ValveInput("fitted", closure_flow(t, hc, rig, [params[k] for k in PARAM_NAMES]), params,
                          dict(old.get("se", {})), old.get("text", ""), k=old.get("nuisance_parameters", FITTED),
                          refined_with=old.get("refined_with", ""), coupling=coupling,
                          shape=old.get("shape", "fitted"), shape_gain=float(old.get("shape_gain", math.nan)))
    if shape == "auto":
        return choose_closure(t, d, rig, window_s, TimeDomainModel(rig, t), coupling=hc)
    return fit_closure(t, d, rig, window_s, TimeDomainModel(rig, t), coupling=hc)


def result_flow(settings: dict, t, h, rig: Rig, position_pct=None) -> np.ndarray | None:
    """The flow at the valve a stored fit was driven by (its ``settings["manoeuvre"]``), rebuilt on the
    grid t (s from the trigger) from the head perturbation h there and the recorded position: what a
    figure needs to draw the fitted models. None for fits made before the manoeuvre was an input (the
    rig's sigmoid)."""
    man = (settings or {}).get("manoeuvre")
    if not man:
        return None
    t = np.asarray(t, dtype=float)
    source = man.get("source")
    if source == "rig":
        return flow_perturbation(t, rig)
    hc = _coupling(t, np.asarray(h, dtype=float), rig)
    if source == "position":
        if position_pct is None:  # (a figure without the position record: the commanded one stands in)
            m = rig.manoeuvre
            position_pct = commanded_position_pct(t, m.beta_per_s, m.gamma)
        return position_flow(t, hc, closing_position(t, position_pct, rig), rig)
    if source == "fitted":
        hc = closure_coupling(t, h, rig, man.get("coupling_head"), measured=hc)
        return closure_flow(t, hc, rig, [float(man["params"].get(k, 0.0)) for k in PARAM_NAMES])
    return None

