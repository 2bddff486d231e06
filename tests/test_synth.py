"""`velab synth` with each valve and friction law: which model makes the data, and what the run file records."""

from __future__ import annotations

import numpy as np
import pytest

from velab.cli import main
from velab.config import load_material, load_rig
from velab.model import creep_scale, flow_perturbation, valve_flow, valve_head
from velab.moc import moc_head, moc_transient
from velab.runfiles import read_run
from velab.synth import SynthSettings, synth_noise, synth_time_grid, synthesise, with_valve_law
from velab.valvelaw import commanded_position_pct, orifice_flow


def _synth(tmp_path, *extra, name="run.h5"):
    path = tmp_path / name
    assert main(["synth", "--material", "A", "--noise", "0", "--duration", "8", "--pretrigger", "0.5",
                 *extra, "-o", str(path)]) == 0
    return read_run(path)


def _params(rig, mat):
    a = mat.wave_speed_m_s
    return a, np.array([e.J_per_pa for e in mat.elements]) * creep_scale(rig, a), np.array([e.tau_s for e in mat.elements])


def _moc(rig, mat, t):
    """The imposed sigmoid flow through the MOC."""
    return moc_head(rig, *_params(rig, mat), t)


def _orifice(rig, mat, t):
    """The commanded sigmoid in position through the valve's orifice law (the MOC)."""
    m = rig.manoeuvre
    return moc_transient(rig, *_params(rig, mat), t,
                         position=lambda x: commanded_position_pct(x, m.beta_per_s, m.gamma))


def test_linear_friction_imposed_valve_is_the_papers_experiment_bit_for_bit():
    """With linear friction and the imposed valve the data are the full-band frequency model plus the
    seeded noise, exactly as velab synthesised them before nonlinear friction and the valve law existed."""
    rig = with_valve_law(load_rig("perugia").with_changes(friction="linear"), "imposed")
    mat = load_material("A")
    s = SynthSettings()
    t, head, flow, position = synthesise(rig, mat, s)
    n_pre = int(np.count_nonzero(t < 0))
    expected = rig.steady_head_m + valve_head(synth_time_grid(s), rig, mat) + synth_noise(s, t.size - n_pre, n_pre)
    np.testing.assert_array_equal(head, expected)
    np.testing.assert_array_equal(flow, valve_flow(t, rig))
    assert position is None


def test_paper_run_from_the_command_line(tmp_path, capsys):
    """--friction linear --valve imposed: the paper's run file (the frequency model, the sigmoid flow,
    no position channel), its rig stored with the imposed valve."""
    r = _synth(tmp_path, "--friction", "linear", "--valve", "imposed")
    out = capsys.readouterr().out
    assert "frequency-domain model" in out and "imposed sigmoid flow" in out
    assert r.rig.valve.law == "imposed" and r.rig.valve.characteristic == "butterfly"
    assert r.source["valve"] == "imposed" and r.source["head_model"] == "frequency-domain model"
    np.testing.assert_allclose(r.head_perturbation(), valve_head(r.time_s, r.rig, load_material("A")), atol=1e-9)
    np.testing.assert_allclose(r.channels["flow"], valve_flow(r.time_s, r.rig), rtol=0, atol=1e-15)
    assert "valve_position" not in r.channels


def test_default_is_the_rigs_orifice_valve_and_quadratic_friction(tmp_path, capsys):
    """The rig's valve: the sigmoid is the valve's position, the flow obeys the orifice law; the run
    stores the flow the model let through and the position, and the rig with its valve."""
    r = _synth(tmp_path)
    out = capsys.readouterr().out
    assert "quadratic" in out and "time-domain model (MOC)" in out and "orifice law" in out
    assert r.rig.friction == "quadratic" and r.rig == load_rig("perugia") and r.rig.valve.law == "orifice"
    assert r.source["friction"] == "quadratic" and r.source["head_model"] == "time-domain model (MOC)"
    assert r.source["valve"] == "orifice"
    mat = load_material("A")
    ref = _orifice(r.rig, mat, r.time_s)
    np.testing.assert_allclose(r.head_perturbation(), ref.head_m, atol=1e-9)
    q0 = r.rig.steady_flow_m3_s
    np.testing.assert_allclose(r.channels["flow"], q0 + ref.flow_m3_s, rtol=0, atol=1e-15)
    m = r.rig.manoeuvre
    np.testing.assert_array_equal(r.channels["valve_position"], commanded_position_pct(r.time_s, m.beta_per_s,
                                                                                       m.gamma))
    assert r.channel_units["valve_position"] == "%"
    # the stored flow is the orifice law's on the stored position and the (noise-free) head
    law = orifice_flow(r.rig.valve.opening(r.channels["valve_position"]), r.head_perturbation(), q0,
                       r.rig.valve_head_m)
    assert np.abs(r.channels["flow"] - law).max() < 2e-4 * q0
    # not the imposed sigmoid's flow, nor its head
    assert np.abs(r.channels["flow"] - valve_flow(r.time_s, r.rig)).max() > 0.2 * q0
    assert np.sqrt(np.mean((r.head_perturbation() - _moc(r.rig, mat, r.time_s)) ** 2)) > 0.5


def test_valve_option_overrides_the_rigs_law(tmp_path):
    r = _synth(tmp_path, "--valve", "imposed", name="imp.h5")
    assert r.rig.valve.law == "imposed" and r.source["head_model"] == "time-domain model (MOC)"
    np.testing.assert_allclose(r.head_perturbation(), _moc(r.rig, load_material("A"), r.time_s), atol=1e-9)
    np.testing.assert_allclose(r.channels["flow"], r.rig.steady_flow_m3_s + flow_perturbation(r.time_s, r.rig),
                               rtol=0, atol=1e-15)
    # linear friction with the orifice valve is still nonlinear: the MOC
    o = _synth(tmp_path, "--friction", "linear", "--valve", "orifice", name="orf.h5")
    assert o.rig.valve.law == "orifice" and o.source["head_model"] == "time-domain model (MOC)"
    np.testing.assert_allclose(o.head_perturbation(), _orifice(o.rig, load_material("A"), o.time_s).head_m,
                               atol=1e-9)


@pytest.mark.parametrize("friction, unsteady, model", [
    ("none", None, "frequency"), ("linear", "vardy-brown", "frequency"), ("quadratic", "brunone", "time"),
    ("linear", "brunone", "time"),
])
def test_each_friction_law(tmp_path, capsys, friction, unsteady, model):
    extra = ["--friction", friction, "--valve", "imposed"] + (["--friction-unsteady", unsteady] if unsteady else [])
    r = _synth(tmp_path, *extra)
    assert model in capsys.readouterr().out
    assert r.rig.friction == friction and r.rig.friction_unsteady == (unsteady or "none")
    mat = load_material("A")
    ref = valve_head(r.time_s, r.rig, mat) if model == "frequency" else _moc(r.rig, mat, r.time_s)
    np.testing.assert_allclose(r.head_perturbation(), ref, atol=1e-9)


def test_the_laws_make_different_data(tmp_path):
    heads = {law: _synth(tmp_path, "--friction", law, name=f"{law}.h5").head_perturbation()
             for law in ("quadratic", "linear", "none")}
    # the first surge barely depends on the law, the decay does: no friction decays least
    t = _synth(tmp_path, "--friction", "none", name="t.h5").time_s
    late = t > 5.0
    ptp = {law: np.ptp(h[late]) for law, h in heads.items()}
    assert ptp["none"] > ptp["quadratic"] > ptp["linear"]


def test_info_shows_the_friction_law(tmp_path, capsys):
    path = tmp_path / "v.h5"
    assert main(["synth", "--duration", "2", "--friction-unsteady", "vardy-brown", "-o", str(path)]) == 0
    capsys.readouterr()
    assert main(["info", str(path)]) == 0
    line = [x for x in capsys.readouterr().out.splitlines() if x.strip().startswith("friction")]
    assert len(line) == 1 and "quadratic" in line[0] and "Vardy-Brown" in line[0] and "Blasius" in line[0]


def test_bad_friction_option_is_a_usage_error(tmp_path, capsys):
    assert main(["synth", "--friction", "darcy", "-o", str(tmp_path / "x.h5")]) == 2
    err = capsys.readouterr().err
    assert "--friction 'darcy': choose from quadratic, linear, none" in err and err.count("\n") == 1
    assert not (tmp_path / "x.h5").exists()


def test_rate_must_resolve_the_orifice_flow(tmp_path, capsys):
    """A butterfly on the orifice law closes the flow about twice as fast as the sigmoid in position:
    a rate that resolves the imposed sigmoid (62 Hz) does not resolve it."""
    assert main(["synth", "--rate", "80", "--duration", "2", "-o", str(tmp_path / "x.h5")]) == 2
    err = capsys.readouterr().err
    assert "cannot resolve the manoeuvre" in err and err.count("\n") == 1
    assert main(["synth", "--rate", "80", "--duration", "2", "--valve", "imposed", "-o", str(tmp_path / "y.h5")]) == 0
