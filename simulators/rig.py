"""ONE physical model of the whole simulated rig: reservoir - HDPE pipe - butterfly valve.

Every simulated device (Modbus ADC, flowmeter, valve actuator, the colleague's
streaming ADC) samples this object; none has physics of its own.

* Before the trigger: steady flow Q0, head ``rig.steady_head_m`` at the transducer.
* The actuator moves the butterfly valve along the commanded sigmoid *in position*
  (``velab.valvelaw.commanded_position_pct``)::

      p(tau) = end + (100 - end) / (1 + exp(beta tau + gamma)),   tau = t - trigger_time

  stopped where it is by a hold or a seizure. The actuator reports that position, the
  ADC's position channel shows it.
* The flow and the head come from the rig's valve law (``rig.valve``, physics.md
  section 10) through velab's own models (``velab.synth.transient``): "orifice" (the
  rig files' default): the flow obeys the orifice law of the valve pair on that
  position, Q = Q0 tau(p) sqrt((Hv0 + h)/Hv0), solved with the head by the time-domain
  model (MOC) with the rig's friction; "imposed" (stored rigs from before the valve law):
  the flow Q0 p / 100 is imposed, and the head is the frequency-domain model's for linear
  friction laws, the MOC's otherwise. The flowmeter shows that flow. Both are computed
  once per arm/hold/seizure on a fine grid and interpolated.
* Transducer: gauge pressure = head * rho * g, 4-20 mA over 0..full scale, plus
  Gaussian noise that is a deterministic function of (seed, channel, time), so any
  two devices sampling the same instant see the same value.
* Several transducers (the rig's ``[[transducers]]``): one model run gives the head at every
  section (``velab.synth.transient_at_sections``: the MOC's ``sections_m``), each on its own steady
  head (``Rig.steady_head_at_m``) with its own noise. Wiring: the valve's transducer
  (``rig.head_section``) on input 0, the valve position on input 1, the others on inputs 2 and 3 in
  the rig file's order (``input_of``).

Times are seconds on the clock's axis (``clock.now()``). Thread-safe: device
servers run in their own threads.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, replace

import numpy as np

from velab.config import Material
from velab.errors import ConfigError
from velab.rig import GRAVITY_M_S2, Manoeuvre, Rig
# the actuator's state codes are the register contract: one definition, the driver's
from velab.drivers.valve import ValveState  # noqa: F401 - re-exported for the simulators and tests
from velab.simulators.rig_faults import (  # noqa: F401 - RigFaults, FAULT_FOLLOWING_ERROR re-exported
    FAULT_FOLLOWING_ERROR,
    RigFaults,
    apply_input_faults,
    due_seizures,
    flow_faults_at,
    pending_seize,
)
from velab.simulators.schedule import RunInstants
from velab.synth import transient, transient_at_sections, uses_frequency_model
from velab.valvelaw import commanded_position_pct

N_ANALOG = 4  # ch0 pressure, ch1 valve position, ch2-3 spare (or the rig's other transducers)
PRESSURE_INPUT, POSITION_INPUT = 0, 1
SECTION_INPUTS = (2, 3)  # the inputs of the rig's transducers other than the valve's, in the rig file's order
SECTION_NOISE_STREAM = 3  # hashed_normal streams: 0 pressure, 1 position, 2 flow, 3.. the other transducers


# fault bits of the actuator (shared with the actuator simulator and driver profile)
FAULT_DRIVE = 0x02
FAULT_SUPPLY_PRESSURE = 0x04
FAULT_PARAMETERS = 0x10


class CommandRefused(Exception):
    """A valve command not allowed in the current state (the actuator answers a Modbus exception)."""

    def __init__(self, message: str, code: int = 3):
        super().__init__(message)
        self.code = code


@dataclass(frozen=True)
class _Transient:
    """One triggered manoeuvre: the valve's position, the head and the flow on a fine grid of tau."""

    trigger_time: float
    beta: float
    gamma: float
    end_pct: float
    dt: float
    position: np.ndarray  # % open on the grid
    head: np.ndarray  # head perturbation (m) on the grid at the valve's transducer
    flow: np.ndarray  # flow through the valve (m3/s) on the grid
    volume: np.ndarray  # integral of Q from the trigger (m3) on the grid
    freeze_tau: float | None  # hold / seizure instant (position frozen after it)
    done_tau: float  # position within 0.1 % of the end: state DONE
    others: np.ndarray | None = None  # head perturbations (m) at the other transducers, (transducers, grid)
    # beyond the grid (tau > its end): each transducer's head perturbation relaxes from its last value to where
    # the rig settles (``final``: the valve's transducer first, then the others) with time constant ``tail_s``
    final: tuple = ()
    tail_s: float = math.inf


def _splitmix64(x: np.ndarray) -> np.ndarray:
    with np.errstate(over="ignore"):
        x = x + np.uint64(0x9E3779B97F4A7C15)
        x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        return x ^ (x >> np.uint64(31))


def hashed_normal(seed: int, stream: int, t: np.ndarray) -> np.ndarray:
    """Standard normal noise, a pure function of (seed, stream, t rounded to 1 us)."""
    idx = np.round(np.asarray(t, dtype=float) * 1e6).astype(np.int64).astype(np.uint64)
    with np.errstate(over="ignore"):
        key = idx * np.uint64(0x100000001B3) + np.uint64((seed * 1_000_003 + stream * 7919) & 0xFFFFFFFFFFFF)
    h = _splitmix64(key)
    u1 = ((h >> np.uint64(40)).astype(np.float64) + 0.5) / 2.0**24
    u2 = ((h & np.uint64(0xFFFFFF)).astype(np.float64) + 0.5) / 2.0**24
    return np.sqrt(-2.0 * np.log(u1)) * np.cos(2 * np.pi * u2)


# seconds of transient computed on arm: a default 30 s recording is the model's to its end (beyond it the
# head relaxes to where the rig settles: SimulatedRig._tail)
TRANSIENT_S = 32.0
# the continuation's relaxation time: at least this, at most TAIL_MAX_S (the envelope's own decay between)
TAIL_MIN_S, TAIL_MAX_S = 1.0, 60.0


class SimulatedRig:
    """The whole rig's physics, sampled by every simulated device.

    Parameters
    ----------
    rig, material : velab configuration (``load_rig("perugia")``, ``load_material("A")``).
    clock : a ``velab.simulators.clock`` clock; all times are on its axis.
    seed : noise seed.
    pressure_noise_fs : transducer noise, standard deviation as a fraction of full scale.
    flow_noise_rel : flowmeter noise, relative standard deviation.
    flow_update_s : flowmeter refresh period (MAG 6000: 0.5 s).
    grid_dt_s, transient_s : grid of the precomputed transient (``transient_s`` s after the trigger, 32 by
        default: the default 30 s record). Beyond it the head is continued by the model's end state: it relaxes
        from the grid's last value to where the rig settles (a closed valve: the reservoir's head at every
        transducer; a valve left partly open or held: the mean of the grid's last pipe period) with the
        transient's own decay time, never a flat hold.
    """

    def __init__(self, rig: Rig, material: Material, clock, seed: int = 0, *,
                 pressure_noise_fs: float = 2e-4, position_noise_pct: float = 0.02,
                 flow_noise_rel: float = 2e-3, flow_update_s: float = 0.5,
                 grid_dt_s: float = 2e-4, transient_s: float = TRANSIENT_S):
        self.rig = rig
        self.material = material
        self.clock = clock
        self.seed = int(seed)
        self.pressure_noise_fs = pressure_noise_fs
        self.position_noise_pct = position_noise_pct
        self.flow_noise_rel = flow_noise_rel
        self.flow_update_s = flow_update_s
        self.grid_dt_s = grid_dt_s
        self.transient_s = transient_s
        valve = rig.head_section
        # the transducers other than the valve's, each on its input (SECTION_INPUTS)
        self.others = tuple(x for x in rig.sections if x != valve)
        if len(self.others) > len(SECTION_INPUTS):
            raise ConfigError(f"rig {rig.name!r}: {len(rig.sections)} transducers; the simulated ADCs have inputs "
                              f"for {len(SECTION_INPUTS) + 1} (the valve's on input 0, the others on inputs "
                              f"{', '.join(map(str, SECTION_INPUTS))})")
        # every section from one model run (a rig whose only transducer is at the valve: transient's head)
        self._sections = bool(self.others) or valve.position_m != rig.pipe.length_m
        self._valve_index = rig.sections.index(valve)
        self._steady_heads = (rig.steady_head_at_m(valve.position_m) if self._sections else rig.steady_head_m,
                              *(rig.steady_head_at_m(x.position_m) for x in self.others))
        self.faults = RigFaults()
        self.schedule = None  # a velab.simulators.schedule.FaultSchedule (faults at run instants)
        self.instants = RunInstants(clock.now())  # arm / trigger instants, for the schedule
        self._lock = threading.RLock()
        m = rig.manoeuvre
        self._beta, self._gamma, self._end = m.beta_per_s, m.gamma, 0.0
        self._state = ValveState.IDLE
        self._armed: _Transient | None = None
        self._arming = False  # an ARM's transient being computed (arm(background=True))
        self._arm_gen = 0  # the arming in force: a cancelled one's result is dropped
        self._tr: _Transient | None = None
        self._stopped_state: ValveState | None = None  # HOLDING / ABORTED set by command
        self._vol_base = 0.0
        self._t_base = clock.now()
        self._trigger_count = 0
        self._fault_bits_latched = 0
        if not uses_frequency_model(rig):
            from velab.moc import warm_up  # numba, only for the time-domain model

            warm_up()  # compile or load the MOC kernel now, not in arm() while a client waits

    # ------------------------------------------------------------ derived constants
    @property
    def rho_g(self) -> float:
        return self.rig.fluid.density_kg_m3 * GRAVITY_M_S2

    @property
    def full_scale_pa(self) -> float:
        return self.rig.transducer.full_scale_pa

    @property
    def trigger_time(self) -> float | None:
        tr = self._tr
        return None if tr is None else tr.trigger_time

    @property
    def trigger_count(self) -> int:
        return self._trigger_count

    @property
    def manoeuvre(self) -> tuple[float, float, float]:
        """(beta 1/s, gamma, end position % open) currently commanded."""
        return self._beta, self._gamma, self._end

    # ------------------------------------------------------------ valve commands
    def set_manoeuvre(self, beta_per_s: float, gamma: float, end_position_pct: float = 0.0) -> None:
        with self._lock:
            if self.state() not in (ValveState.IDLE, ValveState.DONE, ValveState.ABORTED):
                raise CommandRefused(f"manoeuvre cannot change while {self.state().name}", code=6)
            if not (beta_per_s > 0 and math.isfinite(beta_per_s) and math.isfinite(gamma)
                    and 0.0 <= end_position_pct <= 100.0):
                raise CommandRefused(f"invalid manoeuvre beta={beta_per_s} gamma={gamma} end={end_position_pct}")
            self._beta, self._gamma, self._end = float(beta_per_s), float(gamma), float(end_position_pct)

    def arm(self, background: bool = False) -> None:
        """Precompute the transient of the commanded manoeuvre (so the trigger is instant); ARMED when done.

        ``background``: as the actuator does on its ARM command: the command is checked now (a refusal is
        the reply), the computation runs in a thread and the state stays IDLE until it is ARMED (the driver
        waits for ARMED). It takes 0.5-1.2 s of CPU on the reference rig the first time (the step's
        frequency model), seconds on a loaded host: done on the Modbus server's loop it delayed every
        reply of the device past the client's timeout. A trigger, abort or reset meanwhile cancels it."""
        with self._lock:
            st = self.state()
            if st is ValveState.FAULT:
                raise CommandRefused("actuator in FAULT: reset first", code=4)
            if st not in (ValveState.IDLE, ValveState.ARMED):
                raise CommandRefused(f"cannot arm while {st.name} (reset first)")
            seize = pending_seize(self)  # a seizure scheduled at trigger+tau is part of this stroke
            if seize is not None:
                self.faults.valve_fault_after_s, self.faults.valve_fault_bits = seize
            self.instants.mark("arm", self.clock.now())
            self._arm_gen += 1
            self._arming = True
            gen = self._arm_gen
        if background:
            threading.Thread(target=self._finish_arm, args=(gen,), name="sim-valve-arming", daemon=True).start()
        else:
            self._finish_arm(gen)

    def _finish_arm(self, gen: int) -> None:
        """The armed transient, computed outside the lock (the status stays readable); dropped if the arming
        was cancelled, computed again if the manoeuvre or a pending seizure changed meanwhile."""
        while True:
            with self._lock:
                if gen != self._arm_gen:
                    return
                inputs = self._arm_inputs()
            beta, gamma, end, fault_tau = inputs
            armed = self._compute(0.0, beta, gamma, end, freeze_tau=fault_tau)
            with self._lock:
                if gen != self._arm_gen:
                    return
                if self._arm_inputs() != inputs:
                    continue
                self._armed = armed
                self._arming = False
                self._state = ValveState.ARMED
                return

    def _arm_inputs(self) -> tuple:
        """What the armed transient is computed from (under the lock): the manoeuvre and a pending seizure."""
        return self._beta, self._gamma, self._end, self.faults.valve_fault_after_s

    def _cancel_arming(self) -> None:
        self._arm_gen += 1
        self._arming = False

    def trigger(self, at: float | None = None) -> float:
        with self._lock:
            if self.state() is not ValveState.ARMED or self._armed is None:
                raise CommandRefused(f"cannot trigger while {self.state().name} (arm first)")
            t = self.clock.now() if at is None else float(at)
            self._cancel_arming()  # a re-arm still computing (the armed transient is this manoeuvre's)
            self._tr = replace(self._armed, trigger_time=t)
            self._armed = None
            self._state = ValveState.RUNNING
            self._stopped_state = None
            self._trigger_count += 1
            self.instants.mark("trigger", t)
            return t

    def hold(self, at: float | None = None) -> None:
        """Freeze the valve where it is (HOLDING); the transient follows the frozen position."""
        self._stop(ValveState.HOLDING, at)

    def abort(self, at: float | None = None) -> None:
        """Cancel an armed manoeuvre, or stop a running one where it is (ABORTED)."""
        with self._lock:
            if self.state() is ValveState.ARMED or self._arming:
                self._cancel_arming()
                self._armed = None
                self._state = ValveState.ABORTED
                self._stopped_state = None
                return
        self._stop(ValveState.ABORTED, at)

    def _stop(self, new_state: ValveState, at: float | None) -> None:
        with self._lock:
            st = self.state()
            if st is not ValveState.RUNNING:
                if st in (ValveState.HOLDING, ValveState.ABORTED) and new_state is ValveState.ABORTED:
                    self._stopped_state = ValveState.ABORTED
                    return
                raise CommandRefused(f"no running manoeuvre to stop ({new_state.name}) while {st.name}")
            tr = self._tr
            t = self.clock.now() if at is None else float(at)
            tau = max(0.0, t - tr.trigger_time)
            if tr.freeze_tau is None or tau < tr.freeze_tau:
                new = self._compute(tr.trigger_time, tr.beta, tr.gamma, tr.end_pct, freeze_tau=tau)
                self._tr = new
            self._stopped_state = new_state

    def seize(self, at: float | None = None, bits: int = FAULT_FOLLOWING_ERROR) -> None:
        """Fault: the valve stops where it is at ``at`` (default now) and the actuator goes to FAULT
        with ``bits``; before the trigger it will not move at all. Until RESET."""
        with self._lock:
            t = self.clock.now() if at is None else float(at)
            self.faults.valve_fault_bits = int(bits)
            tr = self._tr
            if tr is None or self.state(t) not in (ValveState.RUNNING, ValveState.HOLDING):
                if tr is None:  # idle or armed: the next stroke seizes at once
                    self.faults.valve_fault_after_s = 0.0
                    if self._armed is not None:
                        a = self._armed
                        self._armed = self._compute(0.0, a.beta, a.gamma, a.end_pct, freeze_tau=0.0)
                return
            tau = max(0.0, t - tr.trigger_time)
            if tr.freeze_tau is not None and tr.freeze_tau <= tau:
                tau = tr.freeze_tau  # already stopped (HOLD): it seizes there
            else:
                self._tr = self._compute(tr.trigger_time, tr.beta, tr.gamma, tr.end_pct, freeze_tau=tau)
            self.faults.valve_fault_after_s = tau
            self._stopped_state = None

    def apply_due_seizures(self, t: float | None = None) -> None:
        """Scheduled seizures anchored at start / arm / an absolute time whose instant has come."""
        t = self.clock.now() if t is None else t
        for entry, t0, bits in due_seizures(self, t):
            if getattr(entry, "_seized_at", None) != t0:
                entry._seized_at = t0
                self.seize(t0, bits)

    def reset(self) -> None:
        """Back to steady state, valve open (the operator re-opened it and waited; a simplification)."""
        with self._lock:
            now = self.clock.now()
            self._vol_base = self.totalizer_m3(now)
            self._t_base = now
            self._cancel_arming()
            self._tr = None
            self._armed = None
            self._stopped_state = None
            self._state = ValveState.IDLE
            self.faults.valve_fault_after_s = None

    def state(self, t: float | None = None) -> ValveState:
        """The valve state at time t (default now)."""
        with self._lock:
            if self._tr is None:
                return self._state
            tr = self._tr
            t = self.clock.now() if t is None else t
            tau = t - tr.trigger_time
            fault_tau = self.faults.valve_fault_after_s
            if fault_tau is not None and tr.freeze_tau is not None and tau >= tr.freeze_tau - 1e-9 and \
                    abs(tr.freeze_tau - fault_tau) < 1e-12:
                return ValveState.FAULT
            if self._stopped_state is not None:
                return self._stopped_state
            return ValveState.DONE if tau >= tr.done_tau else ValveState.RUNNING

    def fault_bits(self, t: float | None = None) -> int:
        return self.faults.valve_fault_bits if self.state(t) is ValveState.FAULT else self.faults.valve_warning_bits

    def valve_status(self) -> tuple[ValveState, int, float, float, int]:
        """(state, fault bits, position %, time since trigger s, trigger count) at one instant, read under
        the rig's lock: a real actuator's controller fills its status block in one cycle, so a TRIGGER
        arriving from another connection can never fall between the state and the position of one reply
        (it did: an "ARMED" reply at 98.6 % open, 40 ms into the stroke)."""
        with self._lock:
            now = self.clock.now()
            self.apply_due_seizures(now)  # a seizure scheduled at this instant shows in this very reply
            return (self.state(now), self.fault_bits(now), float(self.valve_position(np.array([now]))[0]),
                    self.time_since_trigger(now), self.trigger_count)

    def time_since_trigger(self, t: float | None = None) -> float:
        tr = self._tr
        if tr is None:
            return 0.0
        return max(0.0, (self.clock.now() if t is None else t) - tr.trigger_time)

    # ------------------------------------------------------------ the transient
    @staticmethod
    def _position(tau: np.ndarray, beta, gamma, end, freeze_tau) -> np.ndarray:
        """Where the actuator has moved the valve tau s after the trigger (% open): the commanded
        sigmoid, stopped at freeze_tau."""
        tau = np.maximum(np.asarray(tau, dtype=float), 0.0)
        if freeze_tau is not None:
            tau = np.minimum(tau, freeze_tau)
        return commanded_position_pct(tau, beta, gamma, end)

    def _compute(self, trigger_time, beta, gamma, end, freeze_tau) -> _Transient:
        dt = self.grid_dt_s
        tau = np.arange(0.0, self.transient_s + dt / 2, dt)
        position = self._position(tau, beta, gamma, end, freeze_tau)
        rig_c = self.rig.with_changes(manoeuvre=Manoeuvre(beta_per_s=beta, gamma=gamma))
        standard = end == 0.0 and freeze_tau is None
        # the rig's valve law on the position, the rig's friction law (velab.synth.transient picks the model)
        moved = None if standard else (lambda x: self._position(x, beta, gamma, end, freeze_tau))
        others = None
        if self._sections:  # every transducer's head from one run of the same model
            heads, q = transient_at_sections(tau, rig_c, self.material, position=moved)
            head = heads[self._valve_index]
            others = np.array([heads[self.rig.sections.index(x)] for x in self.others]).reshape(len(self.others), -1)
        else:
            head, q = transient(tau, rig_c, self.material, position=moved)
        flow = self.rig.steady_flow_m3_s + q
        volume = np.concatenate([[0.0], np.cumsum(0.5 * (flow[1:] + flow[:-1]) * dt)])
        done_tau = rig_c.manoeuvre.closed_s
        final, tail_s = self._tail(head, others, standard)
        return _Transient(trigger_time, beta, gamma, end, dt, position, head, flow, volume, freeze_tau, done_tau,
                          others, final, tail_s)

    def _tail(self, head: np.ndarray, others: np.ndarray | None, closed: bool) -> tuple[tuple, float]:
        """Where each transducer's head perturbation settles after the grid, and how fast it gets there.

        A valve closed for good stops the flow: the head everywhere tends to the reservoir's (no friction loss
        left), i.e. the perturbation to reservoir - steady head. Otherwise (partly open, held, seized) the
        grid's last pipe period's mean. The time constant is the envelope's decay over the grid's last
        periods (the spread of the last period against the one before), within [TAIL_MIN_S, TAIL_MAX_S]."""
        dt = self.grid_dt_s
        period = 4.0 * self.rig.pipe.length_m / max(self.material.wave_speed_m_s, 1.0)
        k = max(2, int(round(period / dt)))
        rows = [head] + ([] if others is None else list(others))
        final = []
        for i, h in enumerate(rows):
            if closed:
                final.append(self.rig.reservoir_head_m - self._steady_heads[i])
            else:
                final.append(float(np.mean(h[-k:])) if h.size else 0.0)
        tail_s = TAIL_MAX_S
        if head.size >= 3 * k:
            last, before = float(np.std(head[-k:])), float(np.std(head[-2 * k:-k]))
            if 0.0 < last < before:
                tail_s = period / math.log(before / last)
        return tuple(final), float(min(max(tail_s, TAIL_MIN_S), TAIL_MAX_S))

    def _interp(self, tr: _Transient, arr: np.ndarray, tau: np.ndarray) -> np.ndarray:
        x = np.clip(tau / tr.dt, 0.0, arr.size - 1.0)
        i = np.minimum(x.astype(np.int64), arr.size - 2)
        f = x - i
        return arr[i] * (1 - f) + arr[i + 1] * f

    # ------------------------------------------------------------ signals (vectorised)
    def valve_position(self, t) -> np.ndarray:
        """The valve's position, % open (100 = open), where the actuator moved it; without noise."""
        t = np.asarray(t, dtype=float)
        tr = self._tr
        if tr is None:
            return np.full(t.shape, 100.0)
        tau = t - tr.trigger_time
        pos = self._interp(tr, tr.position, np.maximum(tau, 0.0))
        return np.where(tau < 0, 100.0, pos)

    def flow_m3_s(self, t) -> np.ndarray:
        """True flow through the valve (m3/s, the rig's valve law), without meter noise or refresh."""
        t = np.asarray(t, dtype=float)
        q0 = self.rig.steady_flow_m3_s
        tr = self._tr
        if tr is None:
            return np.full(t.shape, q0)
        tau = t - tr.trigger_time
        return np.where(tau < 0, q0, self._interp(tr, tr.flow, np.maximum(tau, 0.0)))

    def head_m(self, t, transducer: int = 0) -> np.ndarray:
        """Head at a transducer (m), without noise: 0 the valve's (``rig.head_section``), k >= 1 the k-th
        other one (``others``)."""
        t = np.asarray(t, dtype=float)
        h0 = self._steady_heads[transducer]
        tr = self._tr
        if tr is None:
            return np.full(t.shape, h0)
        tau = t - tr.trigger_time
        h = tr.head if transducer == 0 else tr.others[transducer - 1]
        return np.where(tau < 0, h0, h0 + self._continued(tr, h, np.maximum(tau, 0.0), transducer))

    def _continued(self, tr: _Transient, h: np.ndarray, tau: np.ndarray, transducer: int) -> np.ndarray:
        """The head perturbation on the grid, and beyond its end relaxed towards the rig's end state."""
        out = self._interp(tr, h, tau)
        end = (h.size - 1) * tr.dt
        if not tr.final or not np.any(tau > end):
            return out
        final = tr.final[transducer]
        beyond = final + (h[-1] - final) * np.exp(-np.maximum(tau - end, 0.0) / tr.tail_s)
        return np.where(tau > end, beyond, out)

    def pressure_pa(self, t, transducer: int = 0) -> np.ndarray:
        """Gauge pressure at a transducer (Pa, as :meth:`head_m`), with that transducer's own noise."""
        t = np.asarray(t, dtype=float)
        p = self.head_m(t, transducer) * self.rho_g
        if self.pressure_noise_fs:
            stream = 0 if transducer == 0 else SECTION_NOISE_STREAM + transducer - 1
            p = p + self.pressure_noise_fs * self.full_scale_pa * hashed_normal(self.seed, stream, t)
        return p

    def input_of(self, name: str) -> int:
        """The analogue input a transducer of the rig is wired to (its name as in the rig file)."""
        if name == self.rig.head_section.name:
            return PRESSURE_INPUT
        for k, x in enumerate(self.others):
            if x.name == name:
                return SECTION_INPUTS[k]
        raise KeyError(f"rig {self.rig.name!r} has no transducer {name!r}")

    def clean_inputs(self, t: np.ndarray) -> np.ndarray:
        """Loop currents (mA), shape (n, 4), at times t (clock seconds), without sensor faults.

        ch0: the valve's pressure transducer, 4-20 mA over 0..rig.transducer.full_scale_pa (gauge);
        ch1: valve position feedback, 4-20 mA over 0..100 % open; ch2, ch3: the rig's other transducers
        (as ch0, in the rig file's order), else spare, 4 mA.
        """
        t = np.atleast_1d(np.asarray(t, dtype=float))
        out = np.full((t.size, N_ANALOG), 4.0)
        out[:, PRESSURE_INPUT] = 4.0 + 16.0 * self.pressure_pa(t) / self.full_scale_pa
        for k in range(len(self.others)):
            out[:, SECTION_INPUTS[k]] = 4.0 + 16.0 * self.pressure_pa(t, k + 1) / self.full_scale_pa
        pos = self.valve_position(t)
        if self.position_noise_pct:  # feedback potentiometer noise
            pos = pos + self.position_noise_pct * hashed_normal(self.seed, 1, t)
        out[:, POSITION_INPUT] = 4.0 + 16.0 * pos / 100.0
        return out

    def analog_inputs(self, t: np.ndarray) -> np.ndarray:
        """Loop currents (mA), shape (n, 4), at times t, with the sensor faults in force at each t."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        out = self.clean_inputs(t)
        apply_input_faults(self, t, out)
        return out

    # ------------------------------------------------------------ flowmeter
    def flowmeter_update_time(self, t: float) -> float:
        """The instant of the meter's last refresh at or before t."""
        return math.floor(t / self.flow_update_s) * self.flow_update_s

    def flowmeter_value(self, t: float) -> float:
        """What the flowmeter shows at time t: refreshed every flow_update_s, with noise."""
        f = flow_faults_at(self, t)
        if f.nan:
            return float("nan")
        if f.value is not None:
            return float(f.value)
        tu = self.flowmeter_update_time(t)
        if f.stuck_at is not None and tu > f.stuck_at:
            tu = self.flowmeter_update_time(f.stuck_at)
        q = float(self.flow_m3_s(np.array([tu]))[0])
        if self.flow_noise_rel:
            q *= 1.0 + self.flow_noise_rel * float(hashed_normal(self.seed, 2, np.array([tu]))[0])
        return q

    def flow_alarm_bits(self, t: float) -> int:
        """The flowmeter's alarm word at time t."""
        return flow_faults_at(self, t).alarm_bits

    def totalizer_m3(self, t: float) -> float:
        """Volume through the meter since the simulation started (m3)."""
        q0 = self.rig.steady_flow_m3_s
        tr = self._tr
        if tr is None or t <= tr.trigger_time:
            return self._vol_base + q0 * max(0.0, t - self._t_base)
        before = q0 * max(0.0, tr.trigger_time - self._t_base)
        tau = t - tr.trigger_time
        grid_end = (tr.volume.size - 1) * tr.dt
        if tau <= grid_end:
            after = float(self._interp(tr, tr.volume, np.array([tau]))[0])
        else:
            after = float(tr.volume[-1]) + float(tr.flow[-1]) * (tau - grid_end)
        return self._vol_base + before + after
