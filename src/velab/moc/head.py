"""The valve head on any sample grid from the time-domain model: :func:`moc_head`.

The closure's flow q(t) = Q(t) - Q0 has a small step at the trigger (0.41 % of Q0
for the reference sigmoid) and is continuous after it. A step at an instant between
two samples is what the frequency model represents exactly (a band-limited
fractional delay, as ``velab.model.valve_head``) and the characteristic grid does
not; the continuous rest is the other way round. So:

* linear laws (the steady law "linear" or "none", unsteady "none" or "vardy-brown"):
  the MOC integrates the continuous part q(t) - q(0+) on a grid that starts at the
  trigger; its head is continuous (kinks only) and a cubic (4-point Lagrange)
  interpolation puts it on the samples; the step's response comes from the full-band
  frequency model at the trigger's exact instant. The sum is exact by superposition;
* nonlinear laws ("quadratic", "brunone"): superposition no longer holds, so the MOC
  integrates the whole flow, step included (sharp, on its grid), and the *linear*
  MOC the step alone; their difference (continuous but for the small difference of
  the two fronts) is resampled with a stencil that never straddles a wave front, and
  the frequency model's step response is added. The step then interacts with the
  nonlinear friction as it does in the pipe (up to 4 cm on the imperial rig), and sits
  at its exact instant, band-limited as in ``valve_head``.

With the orifice law at the valve (``opening=``, ``position=``) the flow is not given but
solved with the head, so the transient is nonlinear whatever the friction: the commanded
sigmoid in position starts 0.41 % closed at the trigger, which a butterfly valve turns into
a flow step of 0.03 % of Q0 (the orifice law's own response, the first step of the MOC). That
step is taken apart as for the nonlinear laws: the MOC of the whole transient minus the
linear MOC of that step alone, resampled without straddling a front, plus the frequency
model's response to the step at the trigger's exact instant. The valve flow on the samples
is the step plus the resampled rest, never below zero flow.

With the linear laws ``moc_head`` agrees with ``valve_head`` up to the MOC's own
(second-order) discretisation error, at any trigger offset (docs/model.md).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from threading import Lock

import numpy as np

from velab.rig import Rig
from velab.model import ValveHeadModel, check_position, flow_perturbation
from velab.moc import kernel
from velab.moc.solver import check_laws, run_probes
from velab.valvelaw import commanded_position_pct, imposed_flow

DEFAULT_DT_S = 2e-3  # MOC step when none is given: second order, ~1e-4 hJ on the reference rig (docs/model.md)
_STEP_MODELS: OrderedDict = OrderedDict()
_STEP_HEADS: OrderedDict = OrderedDict()
_STEP_LOCK = Lock()
_STEP_CACHE_SIZE = 8


def default_dt_s(rig: Rig) -> float:
    """MOC step: 2 ms, finer for a manoeuvre faster than beta = 42/s (at least 12 steps per 1/beta,
    so that the cubic resampling of the closure stays below 1e-4 of the Joukowsky head)."""
    return min(DEFAULT_DT_S, 1.0 / (12.0 * rig.manoeuvre.beta_per_s))


def n_reaches(rig: Rig, dt_s: float) -> int:
    """Reaches of the characteristic grid, from the rig's *nominal* wave speed.

    Keeping N independent of the wave speed being evaluated (dt' = L / (N a) moves
    instead) makes the head a smooth function of a: finite-difference Jacobians see
    no jump where N would change.
    """
    if not dt_s > 0:
        raise ValueError(f"dt_s must be positive, got {dt_s}")
    return max(2, int(round(rig.pipe.length_m / (rig.nominal_wave_speed_m_s * dt_s))))


def _cached(cache: OrderedDict, key, make):
    """``cache[key]``, made by ``make()`` (outside the lock: seconds of CPU) on a miss; the least recently used of
    more than ``_STEP_CACHE_SIZE`` entries is dropped."""
    with _STEP_LOCK:
        value = cache.get(key)
        if value is not None:
            cache.move_to_end(key)
            return value
    value = make()
    with _STEP_LOCK:
        cache[key] = value
        while len(cache) > _STEP_CACHE_SIZE:
            cache.popitem(last=False)
    return value


def _step_model(rig: Rig, t: np.ndarray, position_m: float | None = None) -> ValveHeadModel:
    """Full-band frequency model of a unit flow step at the trigger on grid t, the head at the valve or at
    ``position_m`` (cached per rig, grid and position)."""
    key = (rig, float(t[0]), float(t[1] - t[0]), t.size, position_m)
    return _cached(_STEP_MODELS, key,
                   lambda: ValveHeadModel(rig, t, band_hz=None, trigger_step=1.0, position_m=position_m))


def _step_head(rig: Rig, t: np.ndarray, position_m: float | None, a: float, J_rel, tau_s) -> np.ndarray:
    """The unit step's head on grid t (:func:`_step_model`'s), cached per wall as well: 0.3 s of CPU on the
    reference rig's 20 s grid, asked again with the same wall each time a simulated actuator arms or stops."""
    J, tau = np.asarray(J_rel, dtype=float), np.asarray(tau_s, dtype=float)
    key = (rig, float(t[0]), float(t[1] - t[0]), t.size, position_m, float(a), J.tobytes(), tau.tobytes())

    def make():
        head = _step_model(rig, t, position_m).head_params(a, J, tau)
        head.setflags(write=False)  # shared by every caller
        return head
    return _cached(_STEP_HEADS, key, make)


@dataclass(frozen=True)
class ValveTransient:
    """:func:`moc_transient` on the sample grid: perturbations at the valve, zeros before the trigger.

    head_m : head h(t) just upstream of the valve (m above the steady head).
    flow_m3_s : flow q(t) = Q(t) - Q0 through the valve (m^3/s): the imposed flow, or the one the
        orifice law gave.
    section_heads_m : the heads at the sections ``sections_m`` asked for, shape (sections, samples).
    """

    head_m: np.ndarray
    flow_m3_s: np.ndarray
    section_heads_m: np.ndarray | None = None


class _Sections:
    """Sections along the pipe on the characteristic grid: each x = xi dx (xi = x N / L) is read as the
    cubic (4-point Lagrange) interpolation in space of the heads at the nodes around it, each resampled
    in time on its own side of the trigger's fronts; x = L is the valve's own head."""

    def __init__(self, rig: Rig, sections_m, n_reach: int):
        L = rig.pipe.length_m
        self.xs = tuple(float(x) for x in sections_m)
        for x in self.xs:
            check_position(rig, x)
        self.n_reach = N = n_reach
        self.stencils = []  # per section: None (the valve) or (nodes, weights)
        nodes = set()
        for x in self.xs:
            if x == L:
                self.stencils.append(None)
                continue
            xi = x * N / L
            lo = min(max(int(np.floor(xi)) - 1, 0), max(N - 3, 0))
            idx = [j for j in range(lo, min(lo + 4, N + 1))]
            w = [float(np.prod([(xi - k) / (j - k) for k in idx if k != j])) for j in idx]
            self.stencils.append((idx, w))
            nodes.update(idx)
        self.nodes = np.array(sorted(nodes), dtype=np.int64)
        self.column = {int(j): c for c, j in enumerate(self.nodes)}

    def heads(self, valve_head: np.ndarray, probe_heads: np.ndarray, dt: float, t_after: np.ndarray,
              fronts: bool) -> np.ndarray:
        """Each section's head on t_after from the grid series (``fronts``: resampled on one side of
        the trigger's fronts, for a series that has them)."""
        N = self.n_reach
        out = np.zeros((len(self.xs), t_after.size))
        cache = {}
        for s, st in enumerate(self.stencils):
            if st is None:
                out[s] = valve_head
                continue
            for j, w in zip(*st):
                if j not in cache:
                    v = np.ascontiguousarray(probe_heads[:, self.column[j]])
                    cache[j] = (kernel.resample_cubic_fronts(v, dt, t_after, 2 * N, (N - j) % (2 * N),
                                                             (N + j) % (2 * N)) if fronts
                                else kernel.resample_cubic(v, dt, t_after, 0))
                out[s] += w * cache[j]
        return out


def moc_head(rig: Rig, wave_speed_m_s: float, J_rel, tau_s, t_s, *, friction: str | None = None,
             unsteady: str | None = None, dt_s: float | None = None, flow=None, opening=None,
             position=None, sections_m=None) -> np.ndarray:
    """Head perturbation (m) at the valve on the sample grid t_s, from the time-domain model; with
    ``sections_m`` (distances from the reservoir, 0 < x <= L), the heads at those sections instead,
    shape (len(sections_m), len(t_s)) (x = L is the valve's head).

    t_s : uniform grid, s from the trigger; it may start negative (zeros before 0) and
        the trigger may fall between samples.
    wave_speed_m_s, J_rel, tau_s : wave speed a and the Kelvin-Voigt elements as
        dimensionless J'_k (J_k a^2 rho alpha D / e, as ``velab.model.creep_scale``) and
        retardation times tau_k: the parameters of ``ValveHeadModel.head_params(a, J_rel, tau)``.
    friction : steady law ``"quadratic"``, ``"linear"``, ``"none"``; None -> ``rig.friction``.
    unsteady : ``"none"``, ``"vardy-brown"``, ``"brunone"``; None -> ``rig.friction_unsteady``.
    dt_s : MOC step (default :func:`default_dt_s`, 2 ms on the reference rig); the grid has
        N = round(L / (a_nominal dt_s)) reaches and its step is L / (N a).

    The valve node (at most one of these; none: the rig's sigmoid imposed as the flow, whatever
    ``rig.valve`` says -- the paper's model, which the fit's friction correction uses):

    flow : callable t -> q(t), the valve's flow perturbation for t >= 0 (m^3/s), imposed.
        Its value at t = 0 is the step at the trigger.
    opening : callable t -> tau(t), the valve pair's effective opening (1 open, 0 shut) for t >= 0:
        the flow obeys the orifice law Q = Q0 tau sqrt((Hv0 + h)/Hv0), Hv0 = ``rig.valve_head_m``.
    position : callable t -> p(t), the valve's position (% open) for t >= 0, through ``rig.valve``:
        its law "orifice" -> the orifice law with tau = ``rig.valve.opening(p)``; "imposed" ->
        the flow Q0 p / 100 imposed.
    """
    tr = _transient(rig, wave_speed_m_s, J_rel, tau_s, t_s, friction, unsteady, dt_s, flow, opening, position,
                    with_flow=False, sections_m=sections_m)
    return tr.head_m if sections_m is None else tr.section_heads_m


def moc_transient(rig: Rig, wave_speed_m_s: float, J_rel, tau_s, t_s, *, friction: str | None = None,
                  unsteady: str | None = None, dt_s: float | None = None, flow=None, opening=None,
                  position=None, sections_m=None) -> ValveTransient:
    """Head and flow at the valve on the sample grid t_s: :func:`moc_head`'s arguments, and the
    valve's flow as well (what the orifice law made of the opening, or the imposed flow); with
    ``sections_m``, the heads there too (``section_heads_m``)."""
    return _transient(rig, wave_speed_m_s, J_rel, tau_s, t_s, friction, unsteady, dt_s, flow, opening, position,
                      with_flow=True, sections_m=sections_m)


def commanded_opening(rig: Rig):
    """t -> tau(t) of the rig's commanded sigmoid in position (full closure) through ``rig.valve``."""
    m = rig.manoeuvre
    return lambda x: rig.valve.opening(commanded_position_pct(x, m.beta_per_s, m.gamma))


def _transient(rig, wave_speed_m_s, J_rel, tau_s, t_s, friction, unsteady, dt_s, flow, opening, position,
               with_flow: bool, sections_m=None) -> ValveTransient:
    friction = rig.friction if friction is None else friction
    unsteady = rig.friction_unsteady if unsteady is None else unsteady
    check_laws(friction, unsteady)
    if sum(x is not None for x in (flow, opening, position)) > 1:
        raise ValueError("give the valve's flow, its opening or its position, not several")
    if position is not None:
        if rig.valve.law == "orifice":
            opening = lambda x: rig.valve.opening(position(x))  # noqa: E731
        else:
            flow = lambda x: imposed_flow(position(x), rig.steady_flow_m3_s) - rig.steady_flow_m3_s  # noqa: E731
    t = np.asarray(t_s, dtype=float)
    if t.ndim != 1 or t.size < 2:
        raise ValueError("time grid must be a 1-D array of at least 2 samples")
    a = float(wave_speed_m_s)
    if not a > 0:
        raise ValueError(f"wave speed must be positive, got {wave_speed_m_s}")
    out = np.zeros(t.size)
    q_out = np.zeros(t.size) if with_flow else out
    after = t >= 0.0
    n_reach = n_reaches(rig, default_dt_s(rig) if dt_s is None else float(dt_s))
    secs = None if sections_m is None else _Sections(rig, sections_m, n_reach)
    s_out = None if secs is None else np.zeros((len(secs.xs), t.size))
    if not after.any():
        return ValveTransient(out, q_out, s_out)
    probes = None if secs is None else secs.nodes
    dt = rig.pipe.length_m / (n_reach * a)
    n_steps = int(np.floor(t[-1] / dt)) + 4  # the stencil reaches three points past the last sample
    t_grid = np.arange(n_steps) * dt
    t_after = np.ascontiguousarray(t[after])
    # the linear laws closest to the requested ones: the step's response is taken with them
    lin_friction = "none" if friction == "none" else "linear"
    lin_unsteady = "vardy-brown" if unsteady == "vardy-brown" else "none"
    if opening is not None:
        # the orifice law is nonlinear whatever the friction: the MOC takes the whole transient, and the
        # flow step it finds at the trigger (tau(0+) < 1: the commanded sigmoid starts 0.4 % closed) is
        # treated as the nonlinear laws' step below
        tau_grid = np.asarray(opening(t_grid), dtype=float).reshape(-1)
        if tau_grid.size != n_steps:
            raise ValueError("the opening must be a callable t -> tau(t) giving one value per instant")
        head_grid, _, q_grid, probe_grid = run_probes(rig, J_rel, tau_s, None, n_reach, dt, a, friction, unsteady,
                                               opening=tau_grid, probes=probes)
        step = float(q_grid[0])
        if step == 0.0:
            out[after] = kernel.resample_cubic(head_grid, dt, t_after, 0)
            if secs is not None:
                s_out[:, after] = secs.heads(out[after], probe_grid, dt, t_after, False)
            if with_flow:
                q_out[after] = kernel.resample_cubic(q_grid, dt, t_after, 0)
        else:
            step_grid, _, _, step_probes = run_probes(rig, J_rel, tau_s, np.full(n_steps, step), n_reach, dt, a,
                                               lin_friction, lin_unsteady, probes=probes)
            out[after] = kernel.resample_cubic(head_grid - step_grid, dt, t_after, 2 * n_reach)
            if secs is not None:
                s_out[:, after] = secs.heads(out[after], probe_grid - step_probes, dt, t_after, True)
            if with_flow:  # the step sits at the trigger's exact instant; the fronts it sends back stay sharp
                q_out[after] = step + kernel.resample_cubic(q_grid - step, dt, t_after, 2 * n_reach)
        if with_flow:  # the interpolation must not undershoot where the orifice law shut the flow off
            np.maximum(q_out, -rig.steady_flow_m3_s, out=q_out)
    else:
        q_of = (lambda x: flow_perturbation(x, rig)) if flow is None else flow
        step = float(np.asarray(q_of(np.zeros(1)), dtype=float).reshape(-1)[0])
        q_grid = np.asarray(q_of(t_grid), dtype=float)
        # (in laminar flow the "quadratic" law is Poiseuille's, linear)
        linear = (friction == lin_friction or rig.laminar) and unsteady == lin_unsteady
        if linear or step == 0.0:
            head_grid, _, _, probe_grid = run_probes(rig, J_rel, tau_s, q_grid - step, n_reach, dt, a, friction, unsteady,
                                              probes=probes)
            out[after] = kernel.resample_cubic(head_grid, dt, t_after, 0)
            if secs is not None:
                s_out[:, after] = secs.heads(out[after], probe_grid, dt, t_after, False)
        else:
            head_grid, _, _, probe_grid = run_probes(rig, J_rel, tau_s, q_grid, n_reach, dt, a, friction, unsteady,
                                              probes=probes)
            step_grid, _, _, step_probes = run_probes(rig, J_rel, tau_s, np.full(n_steps, step), n_reach, dt, a,
                                               lin_friction, lin_unsteady, probes=probes)
            out[after] = kernel.resample_cubic(head_grid - step_grid, dt, t_after, 2 * n_reach)
            if secs is not None:
                s_out[:, after] = secs.heads(out[after], probe_grid - step_probes, dt, t_after, True)
        if with_flow:
            q_out[after] = np.asarray(q_of(t_after), dtype=float)
    if step != 0.0:
        lin = rig.with_changes(friction=lin_friction, friction_unsteady=lin_unsteady)
        h_step = _step_head(lin, t, None, a, J_rel, tau_s)
        # (the band-limited step's pre-ringing on a sample less than half a step before the
        # trigger, which valve_head keeps, is dropped: zeros before the trigger)
        if secs is not None:
            for i, x in enumerate(secs.xs):
                if secs.stencils[i] is not None:
                    h_x = _step_head(lin, t, x, a, J_rel, tau_s)
                    s_out[i, after] += step * h_x[after]
        out[after] += step * h_step[after]
    if secs is not None:  # a section at the valve is the valve's head, step included
        for i, st in enumerate(secs.stencils):
            if st is None:
                s_out[i] = out
    return ValveTransient(out, q_out, s_out)


def warm_up() -> None:
    """Compile (first use on a machine, a few seconds) or load from numba's cache (about 0.1 s)
    the kernels, on a tiny problem: call it before a thread with a deadline needs the model."""
    q = np.linspace(0.0, -1e-3, 8)
    for mode in (kernel.UNSTEADY_NONE, kernel.UNSTEADY_WEIGHTING):
        kernel.march(2, 1.0, q, kernel.VALVE_IMPOSED, 0.0, kernel.STEADY_QUADRATIC, 0.0, 1e-3, 1e-3, np.ones(1),
                     np.ones(1) * 0.5, np.ones(1), np.ones(1) * 0.1, np.ones(1) * 0.01, 0.1, mode, np.ones(1) * 0.5,
                     np.ones(1), 0.0, 0.0, np.zeros(1, dtype=np.int64))
    kernel.resample_cubic(q, 1.0, np.linspace(0.0, 4.0, 5), 4)
    kernel.resample_cubic_fronts(q, 1.0, np.linspace(0.0, 4.0, 5), 4, 1, 3)
