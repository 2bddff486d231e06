"""Frequency-domain transient model of a reservoir-pipe-valve rig (physics.md sections 3-5).

The head just upstream of the valve is h(s) = Z(s) q(s), with the pipe's
impedance Z(s) = -Zc tanh(mu L). The pipe wall enters only through the
viscoelastic function phi(s) = (a^2 rho alpha D / e) sum_k J_k / (1 + s tau_k).

Time series are rebuilt with the *derivative trick*: the flow increments
dq_n = q_n - q_(n-1) have compact support (the manoeuvre), so their zero-padded
FFT times Z, inverse-transformed and summed, gives the head without the
wrap-around a plain FFT of the step-like q(t) would suffer.

An exponential window (s = sigma + i omega, numerical Laplace inversion) damps
whatever the finite FFT would still wrap around.

Band limit: the sigmoid's spectrum falls like exp(-pi |omega| / beta); the
calibration evaluates Z only below that band (see :class:`ValveHeadModel`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from velab import complexops

from velab.config import Material
from velab.rig import GRAVITY_M_S2, Rig
from velab.friction import unsteady_resistance


def next_fast_len_real(n: int) -> int:
    """The smallest 2^a 3^b 5^c >= n (n >= 1): the real FFT's fast sizes, scipy.fft.next_fast_len(n, real=True).

    numpy.fft, not scipy.fft, transforms the model's series: the same pocketfft (the same numbers here,
    tests/test_model.py), without scipy.fft's import in the processes that never fit (the simulated rig,
    velab synth, a stored fit's report): ~0.6 s alone, 0.13 s after the scipy.linalg that numba loads."""
    if n < 1:
        raise ValueError(f"FFT length must be positive, got {n}")
    best = 1 << max(0, (n - 1).bit_length())  # the power of two
    p5 = 1
    while p5 < best:
        p35 = p5
        while p35 < best:
            best = min(best, p35 << (-(-n // p35) - 1).bit_length())  # p35 2^j, 2^j >= n / p35
            p35 *= 3
        p5 *= 5
    return best


def spring_modulus_pa(rig: Rig, wave_speed_m_s: float) -> float:
    """E0 that gives wave speed a in the thin-walled, K >> E0 limit: a^2 rho alpha D / e."""
    p = rig.pipe
    return wave_speed_m_s**2 * rig.fluid.density_kg_m3 * p.constraint_alpha * p.inner_diameter_m / p.wall_thickness_m


def creep_scale(rig: Rig, wave_speed_m_s: float) -> float:
    """Factor a^2 rho alpha D / e that turns a creep compliance J_k (1/Pa) into its share of phi."""
    return spring_modulus_pa(rig, wave_speed_m_s)


def phi(omega, rig: Rig, material: Material) -> np.ndarray:
    """Complex viscoelastic function phi(i omega) of the pipe wall (dimensionless)."""
    s = 1j * np.asarray(omega, dtype=float)
    J = np.array([e.J_per_pa for e in material.elements])
    tau = np.array([e.tau_s for e in material.elements])
    return _phi_s(s, creep_scale(rig, material.wave_speed_m_s) * J, tau)


def _phi_s(s: np.ndarray, J_rel: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """phi(s) = sum_k J'_k / (1 + s tau_k), J' already scaled (dimensionless)."""
    out = np.zeros(np.shape(s), dtype=complex)
    for Jk, tk in zip(J_rel, tau):
        out += Jk / (1.0 + s * tk)
    return out


def series_impedance(s, rig: Rig) -> np.ndarray:
    """Series impedance per unit length W(s) = s Li + R + R_u(s) (head gradient per flow, s/m^3 per m).

    Li = 1/(gA) is the inertance and R = ``rig.linear_resistance`` the tangent of the
    steady friction at Q0 (0 for friction "none"; for "quadratic" this is the
    linearisation, velab.moc carries the true law). R_u(s) is the weighting-function
    unsteady friction when ``rig.friction_unsteady == "vardy-brown"`` (Zielke's for
    laminar flow): it is linear in q, so this is exact (velab.friction). It vanishes
    at s = 0: the steady friction is unchanged. Brunone's model depends on the sign of
    Q and on |dQ/dx|, so it has no frequency-domain form and adds nothing here.
    The frequency model and the calibration's evaluator both take W from here.
    """
    p = rig.pipe
    gA = GRAVITY_M_S2 * p.area_m2
    s = np.asarray(s, dtype=complex)
    W = s / gA + rig.linear_resistance
    if rig.friction_unsteady == "vardy-brown":
        W = W + unsteady_resistance(s, gravity_area=gA, diameter_m=p.inner_diameter_m,
                                    kinematic_viscosity_m2_s=rig.fluid.kinematic_viscosity_m2_s,
                                    reynolds=rig.reynolds)
    return W


def section_ratio(mu: np.ndarray, x: float, L: float) -> np.ndarray:
    """sinh(mu x) / cosh(mu L) (physics.md section 12), written with decaying exponentials only
    (Re mu >= 0): the plain form overflows where the wall damps the high frequencies."""
    e = np.exp(-2.0 * mu * L)
    return (np.exp(mu * (x - L)) - np.exp(-mu * (x + L))) / (1.0 + e)


def check_position(rig: Rig, position_m: float | None) -> float | None:
    """A section's distance from the reservoir, None for the valve's (x = L is the valve too)."""
    if position_m is None:
        return None
    x = float(position_m)
    L = rig.pipe.length_m
    if not 0.0 < x <= L:
        raise ValueError(f"a section's position must be in (0, {L:g}] m (the pipe's length), got {position_m!r}")
    return None if x == L else x


def _impedance_s(s: np.ndarray, a: float, phi_s: np.ndarray, rig: Rig, W=None,
                 position_m: float | None = None) -> np.ndarray:
    """Z(s) = -Zc tanh(mu L) for s != 0; s == 0 gets the steady -R L. ``W``: the series impedance on s
    if not the rig's own (a fit's equivalent linear friction, velab.fitting.friction). ``position_m``:
    the transfer impedance to the head at x from the reservoir, -Zc sinh(mu x) / cosh(mu L) (steady:
    -R x); None is the valve's (x = L)."""
    x = check_position(rig, position_m)
    p = rig.pipe
    C = GRAVITY_M_S2 * p.area_m2 / a**2
    s = np.asarray(s, dtype=complex)
    zero = s == 0
    s_safe = np.where(zero, 1.0, s)
    Y = s_safe * C * (1.0 + phi_s)  # shunt admittance per unit length
    fast = complexops.ENABLED and s.ndim == 1  # (numpy's complex ufuncs are scalar loops: velab.complexops)
    w = list(np.empty((complexops.WORK, s.size))) if fast else None
    mu = Y * (series_impedance(s_safe, rig) if W is None else W)
    # principal branch: Re(mu) >= 0
    mu = complexops.sqrt(mu, mu, w, np.empty(s.size, dtype=bool)) if fast else np.sqrt(mu)
    if x is None:
        g = mu * p.length_m
        if fast:
            Z = -complexops.divide(mu, Y, mu, w) * complexops.tanh(g, g, w)
        else:
            Z = -(mu / Y) * np.tanh(g)
        return np.where(zero, -rig.linear_resistance * p.length_m, Z)
    Z = -(mu / Y) * section_ratio(mu, x, p.length_m)
    return np.where(zero, -rig.linear_resistance * x, Z)


def impedance(omega, rig: Rig, material: Material, position_m: float | None = None) -> np.ndarray:
    """Z(i omega) at the valve (or the transfer impedance to the section at ``position_m`` from the
    reservoir), in m of head per m^3/s of the valve's flow."""
    s = 1j * np.asarray(omega, dtype=float)
    return _impedance_s(s, material.wave_speed_m_s, phi(omega, rig, material), rig, position_m=position_m)


def wave_speed_dispersion(omega, rig: Rig, material: Material) -> np.ndarray:
    """Complex a(omega) = a / sqrt(1 + phi(i omega)); its omega -> 0 limit is the creep-slowed speed."""
    return material.wave_speed_m_s / np.sqrt(1.0 + phi(omega, rig, material))


def flow_perturbation(t_s, rig: Rig) -> np.ndarray:
    """q(t) = Q(t) - Q0 of the sigmoid closure; 0 before the trigger (t < 0)."""
    t = np.asarray(t_s, dtype=float)
    m = rig.manoeuvre
    q0 = rig.steady_flow_m3_s
    arg = np.clip(m.beta_per_s * t + m.gamma, -700, 700)
    q = q0 / (1.0 + np.exp(arg)) - q0
    return np.where(t >= 0, q, 0.0)


def valve_flow(t_s, rig: Rig) -> np.ndarray:
    """Absolute flow through the valve, Q0 before the trigger."""
    return rig.steady_flow_m3_s + flow_perturbation(t_s, rig)


@dataclass(frozen=True)
class Band:
    """Which FFT bins are evaluated."""

    n_fft: int
    n_bins: int  # bins 0..n_bins-1 are evaluated, the rest are taken as zero
    f_max_hz: float


def manoeuvre_band_hz(rig: Rig, tol: float = 1e-8) -> float:
    """Frequency above which the sigmoid's spectrum is below ``tol`` of its DC value.

    The ideal sigmoid's flow spectrum is (pi/beta)/sinh(pi omega/beta) relative to
    a step's 1/omega, i.e. it decays like 2 exp(-pi omega / beta).
    """
    beta = rig.manoeuvre.beta_per_s
    omega = beta / np.pi * np.log(2.0 / tol)
    return float(omega / (2 * np.pi))


class ValveHeadModel:
    """Head perturbation at the valve for one rig, manoeuvre and time grid.

    Build it once per record, then call :meth:`head` for many materials: the
    flow-increment spectrum and the band are reused, which is what makes
    calibration fast.

    The trigger need not fall on a sample: the sigmoid is sampled at the grid's
    own times, and the 0.41 % flow step it has at the trigger enters the spectrum
    as a delta at its exact instant (a fractional delay, exp(-s tau0)). A short
    lead-in of empty samples before the first one keeps the band-limited step's
    pre-ringing inside the computation, so nothing of the step is lost.

    Parameters
    ----------
    rig : the rig (pipe, fluid, steady flow, manoeuvre).
    t_s : uniform time grid, seconds from the trigger (may start before 0).
    band_hz : highest frequency at which Z is evaluated; ``None`` evaluates every
        FFT bin (the full-band reference), ``"auto"`` uses
        :func:`manoeuvre_band_hz`. Above the band only the trigger's step and the
        sigmoid's slope kink have energy: a band-limited evaluation smooths the
        step symmetrically (a few mm of head at the wave fronts on the reference rig).
    pad : zero-padding factor (>= 2, physics.md section 5).
    sigma_T : exponential-window damping sigma times the padded length; it damps
        what the FFT would wrap around by exp(-sigma_T).
    flow : optional flow perturbation q(t) on the same grid (default: the rig's
        sigmoid); its value at the first sample at or after the trigger is taken as
        the step at the trigger.
    trigger_step : if given, the flow is only a step of this size (m^3/s) at the
        trigger's exact, possibly off-grid, instant (velab.moc integrates the
        continuous rest of a closure in the time domain and adds this step's response).
    position_m : the head at this distance from the reservoir (0 < x <= L) instead of at the
        valve (None, or x = L: the same computation); the valve's flow still drives the pipe.
    """

    LEAD_SAMPLES = 64  # full band: the step's pre-ringing one lead-in away is < 0.2 % of it

    def __init__(self, rig: Rig, t_s, *, band_hz: float | str | None = "auto", pad: float = 2.0,
                 sigma_T: float = 8.0, flow=None, trigger_step: float | None = None,
                 position_m: float | None = None):
        t = np.asarray(t_s, dtype=float)
        self.position_m = check_position(rig, position_m)  # None: at the valve
        if t.ndim != 1 or t.size < 2:
            raise ValueError("time grid must be a 1-D array of at least 2 samples")
        self.rig = rig
        self.t = t
        self.dt = dt = float(t[1] - t[0])
        self.first = int(np.searchsorted(t, -0.5 * dt))  # first sample at or after (about) the trigger
        n = t.size - self.first
        self.n = n
        if band_hz == "auto":
            band_hz = manoeuvre_band_hz(rig)
        lead = self.LEAD_SAMPLES if band_hz is None else max(self.LEAD_SAMPLES, int(np.ceil(4.0 / (band_hz * dt))))
        self.lead = lead
        # internal grid: `lead` empty samples, then the record from `first` on
        t0 = (t[self.first] if n else 0.0) - lead * dt
        t_int = t0 + np.arange(lead + n) * dt
        if trigger_step is not None:
            q = np.where(t_int >= -1e-12 * dt, float(trigger_step), 0.0)
            step = float(trigger_step)
        elif flow is None:
            q = flow_perturbation(t_int, rig)
            step = float(flow_perturbation(np.array([0.0]), rig)[0])
        else:
            q = np.concatenate([np.zeros(lead), np.asarray(flow, dtype=float)[self.first :]])
            step = float(q[lead]) if n else 0.0
        self.n_int = lead + n
        self.n_fft = next_fast_len_real(int(np.ceil(max(pad, 2.0) * self.n_int)))
        self.sigma = sigma_T / (self.n_fft * dt)
        self.growth = np.exp(self.sigma * np.arange(self.n_int) * dt)  # undoes the window after the inverse FFT
        omega = 2 * np.pi * np.fft.rfftfreq(self.n_fft, dt)
        s_all = self.sigma + 1j * omega
        self._after = t_int >= -1e-12 * dt
        self._step_phase = np.exp(s_all * t0)  # exp(-s tau0), tau0 = -t0 the trigger instant on the internal grid
        self.spec = self._flow_spectrum(q, step, zero_lead=flow is not None)
        n_bins = self.spec.size if band_hz is None else min(self.spec.size, int(np.searchsorted(omega, 2 * np.pi * band_hz)) + 1)
        self.band = Band(self.n_fft, n_bins, float(omega[n_bins - 1] / (2 * np.pi)))
        self.s_band = s_all[:n_bins]
        self._spec_band = self.spec[:n_bins]
        # cumulative sum in the frequency domain (see sums_to_time): the windowed increments'
        # partial sums sum_(j<=J) growth_j y_j equal growth_(J+1) w_(J+1) - w_0 with
        # w = irfft(X / (exp(s dt) - 1)), so the fitter's batched columns need no cumsum
        self._expm1 = np.expm1(self.s_band * dt)
        self.spec_sum = self._spec_band / self._expm1
        self._growth_sum = np.exp(self.sigma * np.arange(lead + 1, lead + 1 + n) * dt)

    def _flow_spectrum(self, q: np.ndarray, step: float, zero_lead: bool) -> np.ndarray:
        """Spectrum of the windowed flow increments on the internal grid, the step at the trigger's instant."""
        smooth = q - step * self._after  # continuous at the trigger
        if zero_lead:
            smooth[: self.lead] = 0.0
        return np.fft.rfft(np.diff(smooth, prepend=0.0) / self.growth, self.n_fft) + step * self._step_phase

    def flow_sums(self, flow) -> np.ndarray:
        """:attr:`spec_sum` of another flow on the same grid (``flow`` as the constructor takes it): the
        fitted closure (velab.fitting.manoeuvre) re-drives the model without rebuilding it."""
        q = np.concatenate([np.zeros(self.lead), np.asarray(flow, dtype=float)[self.first :]])
        step = float(q[self.lead]) if self.n else 0.0
        return self._flow_spectrum(q, step, zero_lead=True)[: self.band.n_bins] / self._expm1

    def head_of(self, impedance_spectra: np.ndarray, sums: np.ndarray) -> np.ndarray:
        """Like :meth:`to_time`, with the flow's summed spectrum ``sums`` (:meth:`flow_sums`) instead of
        the model's own; both broadcast over leading axes."""
        z = np.asarray(impedance_spectra) * sums
        buf = np.zeros(z.shape[:-1] + (self.spec.size,), dtype=complex)
        buf[..., : self.band.n_bins] = z
        return self.sums_to_time(buf)

    def impedance(self, a: float, J_rel, tau, W=None) -> np.ndarray:
        """Z on the band's bins for wave speed a and KV elements (J'_k, tau_k); ``W`` the series
        impedance on the band's bins if not the rig's own."""
        return _impedance_s(self.s_band, a, _phi_s(self.s_band, J_rel, tau), self.rig, W, self.position_m)

    def to_time(self, impedance_spectra: np.ndarray) -> np.ndarray:
        """Impedance on the band's bins (..., n_bins) -> head series (..., len(t)).

        Multiplies by the flow-increment spectrum, inverse-transforms, undoes the
        exponential window and sums the increments; zero before the trigger.
        Leading axes are kept (the fitter passes Jacobian columns at once).
        """
        z = np.asarray(impedance_spectra)
        buf = np.zeros(z.shape[:-1] + (self.spec.size,), dtype=complex)
        np.multiply(z, self.spec_sum, out=buf[..., : self.band.n_bins])
        return self.sums_to_time(buf)

    def sums_to_time(self, spectrum: np.ndarray, out: np.ndarray | None = None,
                     work: np.ndarray | None = None) -> np.ndarray:
        """Half spectrum (..., n_fft//2 + 1) of Z times :attr:`spec_sum` -> head series (..., len(t)).

        The summation of the increments is done in the frequency domain: with
        s_k = sigma + i omega_k, sum_(j=0..J) exp(s_k j dt) = (exp(s_k (J+1) dt) - 1) / (exp(s_k dt) - 1),
        so the head after J+1 increments is growth_(J+1) w_(J+1) - w_0, w = irfft(spectrum).
        Same result as a cumulative sum of the inverse-transformed increments (to rounding),
        one pass over the time series fewer. ``out`` (..., len(t)) and ``work`` (..., n_fft),
        if given, are filled instead of allocating (the fitter reuses its buffers: fresh
        multi-megabyte arrays cost page faults every call).
        """
        w = np.fft.irfft(spectrum, self.n_fft, axis=-1, out=work)
        if out is None:
            out = np.zeros(w.shape[:-1] + (self.t.size,))
        elif self.first:
            out[..., : self.first] = 0.0
        o = out[..., self.first :]
        np.multiply(w[..., self.lead + 1 : self.lead + 1 + self.n], self._growth_sum, out=o)
        o -= w[..., :1]
        return out

    def head_params(self, a: float, J_rel, tau) -> np.ndarray:
        """Head perturbation h(t) for wave speed a and KV elements (J'_k = J_k a^2 rho alpha D/e, tau_k)."""
        return self.to_time(self.impedance(a, J_rel, tau))

    def head(self, material: Material) -> np.ndarray:
        """Head perturbation h(t) (m) at the valve for a pipe-wall material."""
        a = material.wave_speed_m_s
        J_rel = np.array([e.J_per_pa for e in material.elements]) * creep_scale(self.rig, a)
        tau = np.array([e.tau_s for e in material.elements])
        return self.head_params(a, J_rel, tau)


def valve_head(t_s, rig: Rig, material: Material, *, band_hz: float | str | None = None,
               position_m: float | None = None) -> np.ndarray:
    """Head perturbation at the valve (m above the steady head) on the grid t_s (s from the trigger),
    or at the section ``position_m`` from the reservoir.

    Full band by default: this is the reference used to synthesise runs.
    """
    return ValveHeadModel(rig, t_s, band_hz=band_hz, position_m=position_m).head(material)
