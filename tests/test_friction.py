"""Friction laws: Darcy factor, weighting functions, the series impedance, and the rig's friction keys."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy import integrate, special

from velab.config import load_rig
from velab.rig import GRAVITY_M_S2, rig_from_dict
from velab.errors import ConfigError
from velab.friction import (
    colebrook,
    darcy_factor,
    vardy_brown_decay,
    weighting_exponentials,
    weighting_laplace,
)
from velab.model import impedance, series_impedance
from velab.config import load_material

PERUGIA_RE = 47687.0


# --------------------------------------------------------------------------- steady


def test_blasius_and_colebrook_agree_for_a_smooth_pipe():
    """At moderate Re the smooth-pipe Colebrook (Prandtl-Karman) and Blasius agree to ~1 %."""
    fb = darcy_factor(PERUGIA_RE, "blasius")
    fc = darcy_factor(PERUGIA_RE, "colebrook", 0.0)
    assert fb == pytest.approx(0.316 * PERUGIA_RE**-0.25)
    assert fc == pytest.approx(fb, rel=0.02)
    assert fc == pytest.approx(0.02111, rel=1e-3)  # Moody chart value for a smooth pipe at Re 4.8e4


def test_colebrook_solves_its_equation_and_roughness_raises_f():
    for re, r in [(5e3, 0.0), (4.8e4, 1e-4), (1e6, 1e-3), (1e8, 0.05)]:
        f = colebrook(re, r)
        assert 1 / math.sqrt(f) == pytest.approx(-2 * math.log10(r / 3.7 + 2.51 / (re * math.sqrt(f))), rel=1e-12)
    assert darcy_factor(1e5, "colebrook", 1e-3) > darcy_factor(1e5, "colebrook", 1e-5) > darcy_factor(1e5, "colebrook", 0)
    # fully rough limit: 1/sqrt(f) = -2 log10(r/3.7), independent of Re
    assert colebrook(1e9, 0.01) == pytest.approx((2 * math.log10(3.7 / 0.01)) ** -2, rel=1e-3)


def test_laminar_is_poiseuille():
    assert darcy_factor(1000.0, "blasius") == darcy_factor(1000.0, "colebrook", 0.01) == pytest.approx(0.064)
    assert darcy_factor(0.0) == 0.0
    with pytest.raises(ValueError):
        darcy_factor(1e5, "moody")


def test_rig_tangent_resistance_per_law():
    rig = load_rig("perugia")
    p = rig.pipe
    R_turb = rig.friction_factor * rig.steady_flow_m3_s / (GRAVITY_M_S2 * p.inner_diameter_m * p.area_m2**2)
    assert rig.linear_resistance == pytest.approx(R_turb)  # quadratic: its tangent at Q0
    assert rig.with_changes(friction="linear").linear_resistance == rig.linear_resistance
    assert rig.with_changes(friction="none").linear_resistance == 0.0
    # laminar: the Poiseuille law is linear, R = 32 nu / (g D^2 A) (not twice the secant)
    lam = rig.with_changes(steady_flow_m3_s=1e-4)
    assert lam.laminar
    nu = rig.fluid.kinematic_viscosity_m2_s
    assert lam.linear_resistance == pytest.approx(32 * nu / (GRAVITY_M_S2 * p.inner_diameter_m**2 * p.area_m2))
    assert lam.linear_resistance * lam.steady_flow_m3_s * p.length_m == pytest.approx(lam.steady_head_loss_m)


# --------------------------------------------------------------------------- unsteady


def test_vardy_brown_decay_values():
    """B* = Re^kappa / 12.86, kappa = log10(15.29 / Re^0.0567) (Vardy & Brown 2003)."""
    kappa = math.log10(15.29 / PERUGIA_RE**0.0567)
    assert vardy_brown_decay(PERUGIA_RE) == pytest.approx(PERUGIA_RE**kappa / 12.86)
    assert 1400 < vardy_brown_decay(PERUGIA_RE) < 1700
    assert vardy_brown_decay(1e6) > vardy_brown_decay(1e5) > vardy_brown_decay(1e4)


def test_vardy_brown_laplace_transform_of_its_weighting_function():
    """W(tau) = A* exp(-B* tau)/sqrt(tau), A* = 1/(2 sqrt(pi)): its transform is 1/(2 sqrt(p + B*))."""
    b = vardy_brown_decay(PERUGIA_RE)
    for p in (0.0, 50.0, 3e3):
        # substitute tau = x^2 to remove the singularity
        val, _ = integrate.quad(lambda x: 2 * math.exp(-(b + p) * x * x) / (2 * math.sqrt(math.pi)), 0, np.inf)
        assert weighting_laplace(np.array([p]), PERUGIA_RE)[0] == pytest.approx(val, rel=1e-9)


def test_zielke_transform_is_the_sum_over_bessel_zeros():
    zeros = special.jn_zeros(2, 200000)
    for p in (0.5, 10 + 3j, 1e4j):
        direct = np.sum(1 / (p + zeros**2)) + 1 / (math.pi * (zeros[-1] + math.pi / 2))  # + tail
        assert weighting_laplace(np.array([p]), 1000.0)[0] == pytest.approx(direct, rel=1e-6)
    assert weighting_laplace(np.array([0.0, 1e-9]), 1000.0) == pytest.approx([1 / 12, 1 / 12], rel=1e-7)


@pytest.mark.parametrize("re", [PERUGIA_RE, 25063.0, 1500.0])
def test_exponential_sums_match_the_transforms(re):
    """The MOC's sum of exponentials has the weighting function's transform to 5e-4 relative (measured 3e-4),
    on the imaginary axis (the frequency response) and the positive real axis."""
    m, n = weighting_exponentials(re)
    assert np.all(m > 0) and np.all(n > 0)
    p = np.concatenate([1j * np.logspace(-3, 9, 120), np.logspace(-3, 9, 40)])
    exact = weighting_laplace(p, re)
    approx = np.sum(m[:, None] / (p[None, :] + n[:, None]), axis=0)
    assert np.abs(approx / exact - 1).max() < 5e-4


def test_series_impedance_and_the_unsteady_resistance():
    rig = load_rig("perugia")
    gA = GRAVITY_M_S2 * rig.pipe.area_m2
    s = np.array([1e-9 + 0j, 0.5 + 3j, 1j * 200.0, 1j * 2e4])
    plain = series_impedance(s, rig)
    np.testing.assert_array_equal(plain, s / gA + rig.linear_resistance)
    vb = rig.with_changes(friction_unsteady="vardy-brown")
    Ru = series_impedance(s, vb) - plain
    # R_u -> 0 as s -> 0 (steady friction unchanged); dissipative (Re R_u > 0) on the imaginary axis
    assert abs(Ru[0]) < 1e-6 * rig.linear_resistance
    assert np.all(Ru[2:].real > 0)
    # at high frequency it grows like sqrt(omega) and dwarfs the steady R
    assert abs(Ru[3]) > 10 * abs(Ru[2]) ** 1 > rig.linear_resistance
    # the valve impedance's DC value -R L is unchanged by the unsteady friction
    mat = load_material("A")
    assert impedance(np.array([0.0, 1e-8]), vb, mat) == pytest.approx(impedance(np.array([0.0, 1e-8]), rig, mat), rel=1e-6)
    # Brunone has no frequency form: nothing is added
    np.testing.assert_array_equal(series_impedance(s, rig.with_changes(friction_unsteady="brunone")), plain)


# --------------------------------------------------------------------------- rig files


RIG = """
[pipe]
length_m = 100.0
inner_diameter_m = 0.1
wall_thickness_m = 0.005
constraint_alpha = 1.0
[flow]
steady_flow_m3_s = 0.003
reservoir_head_m = 30
{flow}
[manoeuvre]
beta_per_s = 32
gamma = -5.5
[transducer]
full_scale_bar = 6
[wave]
nominal_speed_m_s = 350
"""


def _load(tmp_path, flow):
    p = tmp_path / "rig.toml"
    p.write_text(RIG.format(flow=flow))
    return load_rig(p)


def test_friction_keys_defaults_and_values(tmp_path):
    r = _load(tmp_path, "")
    assert (r.friction, r.friction_factor_law, r.roughness_m, r.friction_unsteady) == ("quadratic", "blasius", 0.0, "none")
    r = _load(tmp_path, 'friction = "linear"\nfriction_factor = "colebrook"\nroughness_m = 1.5e-6\n'
                        'friction_unsteady = "brunone"\nbrunone_k3 = 0.03')
    assert (r.friction, r.friction_factor_law, r.roughness_m, r.friction_unsteady, r.brunone_k3) == (
        "linear", "colebrook", 1.5e-6, "brunone", 0.03)
    assert r.friction_factor == pytest.approx(colebrook(r.reynolds, 1.5e-5))
    assert "Colebrook" in r.friction_description and "Brunone k3 = 0.03" in r.friction_description
    # the name before quadratic friction existed
    old = _load(tmp_path, 'friction = "blasius"')
    assert (old.friction, old.friction_factor_law) == ("linear", "blasius")


@pytest.mark.parametrize("flow, where, reason", [
    ('friction = "darcy"', "[flow] friction", "must be one of quadratic, linear, none"),
    ('friction_factor = "moody"', "[flow] friction_factor", "must be one of blasius, colebrook"),
    ('friction_factor = "colebrook"', "[flow] roughness_m", "missing key"),
    ('friction_factor = "colebrook"\nroughness_m = 0.01', "[flow] roughness_m", "at most 5 %"),
    ('roughness_m = 1e-5', "[flow] roughness_m", "only used with friction_factor"),
    ('roughness_m = -1e-5\nfriction_factor = "colebrook"', "[flow] roughness_m", "must not be negative"),
    ('friction_unsteady = "zielke"', "[flow] friction_unsteady", "must be one of none, vardy-brown, brunone"),
    ('brunone_k3 = 0.02', "[flow] brunone_k3", "only used with friction_unsteady"),
    ('friction_unsteady = "brunone"\nbrunone_k3 = 0.5', "[flow] brunone_k3", "must be in (0, 0.2]"),
    ('friction_unsteady = "brunone"\nbrunone_k3 = "high"', "[flow] brunone_k3", "must be a number"),
    ('friction = "blasius"\nfriction_factor = "colebrook"\nroughness_m = 0', "[flow] friction", "old name"),
])
def test_bad_friction_keys_are_one_line_errors(tmp_path, flow, where, reason):
    with pytest.raises(ConfigError) as ei:
        _load(tmp_path, flow)
    msg = str(ei.value)
    assert "\n" not in msg and str(tmp_path / "rig.toml") in msg and where in msg and reason in msg


def test_stored_rigs_round_trip_and_old_run_files_still_read():
    rig = load_rig("perugia").with_changes(friction_unsteady="vardy-brown")
    assert rig_from_dict(json.loads(json.dumps(rig.to_dict()))) == rig
    old = json.loads(json.dumps(rig.to_dict()))
    for key in ("friction_factor_law", "roughness_m", "friction_unsteady", "brunone_k3"):
        del old[key]
    old["friction"] = "blasius"  # what run files written before this change hold
    r = rig_from_dict(old)
    assert (r.friction, r.friction_factor_law, r.friction_unsteady) == ("linear", "blasius", "none")
    assert r.linear_resistance == rig.linear_resistance
    old["friction"] = "none"
    assert rig_from_dict(old).friction == "none" and rig_from_dict(old).linear_resistance == 0.0
    old["friction"] = "turbulent"
    with pytest.raises(ConfigError, match="rig description"):
        rig_from_dict(old)


def test_second_reference_rig_is_plausible():
    """configs/rigs/imperial.toml: another length, bore and flow; the surge (Joukowsky + steady
    head loss, a generous bound for the line packing) stays within the transducer and the pipe rating,
    and the lowest head stays positive (no column separation)."""
    per, imp = load_rig("perugia"), load_rig("imperial")
    assert imp.pipe.length_m > 2 * per.pipe.length_m and imp.pipe.inner_diameter_m < 0.6 * per.pipe.inner_diameter_m
    assert imp.steady_flow_m3_s < 0.5 * per.steady_flow_m3_s and not imp.laminar
    rho_g = imp.fluid.density_kg_m3 * GRAVITY_M_S2
    peak = imp.steady_head_m + imp.joukowsky_head_m() + imp.steady_head_loss_m
    assert peak * rho_g < imp.transducer.full_scale_pa < imp.pipe.pressure_rating_pa
    assert imp.steady_head_m - imp.joukowsky_head_m() > 5.0
