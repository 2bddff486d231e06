"""`velab synth` with each friction law: which model makes the data, and what the run file records."""

from __future__ import annotations

import numpy as np
import pytest

from velab.cli import main
from velab.config import load_material, load_rig
from velab.model import creep_scale, valve_head
from velab.moc import moc_head
from velab.runfile import read_run
from velab.synth import SynthSettings, synth_noise, synth_time_grid, synthesise


def _synth(tmp_path, *extra, name="run.h5"):
    path = tmp_path / name
    assert main(["synth", "--material", "A", "--noise", "0", "--duration", "8", "--pretrigger", "0.5",
                 *extra, "-o", str(path)]) == 0
    return read_run(path)


def _moc(rig, mat, t):
    a = mat.wave_speed_m_s
    J = np.array([e.J_per_pa for e in mat.elements]) * creep_scale(rig, a)
    return moc_head(rig, a, J, np.array([e.tau_s for e in mat.elements]), t)


def test_linear_friction_is_the_papers_experiment_bit_for_bit():
    """With linear friction the data are the full-band frequency model plus the seeded noise,
    exactly as velab synthesised them before nonlinear friction existed."""
    rig = load_rig("perugia").with_changes(friction="linear")
    mat = load_material("A")
    s = SynthSettings()
    t, head, _ = synthesise(rig, mat, s)
    n_pre = int(np.count_nonzero(t < 0))
    expected = rig.steady_head_m + valve_head(synth_time_grid(s), rig, mat) + synth_noise(s, t.size - n_pre, n_pre)
    np.testing.assert_array_equal(head, expected)


def test_default_is_the_rigs_quadratic_friction_through_the_moc(tmp_path, capsys):
    r = _synth(tmp_path)
    out = capsys.readouterr().out
    assert "quadratic" in out and "time-domain model (MOC)" in out
    assert r.rig.friction == "quadratic" and r.rig == load_rig("perugia")
    assert r.source["friction"] == "quadratic" and r.source["head_model"] == "time-domain model (MOC)"
    mat = load_material("A")
    np.testing.assert_allclose(r.head_perturbation(), _moc(r.rig, mat, r.time_s), atol=1e-9)
    lin = valve_head(r.time_s, r.rig.with_changes(friction="linear"), mat)
    late = r.time_s > 5.0
    assert np.sqrt(np.mean((r.head_perturbation() - lin)[late] ** 2)) > 0.5  # not the linear model's data


@pytest.mark.parametrize("friction, unsteady, model", [
    ("none", None, "frequency"), ("linear", "vardy-brown", "frequency"), ("quadratic", "brunone", "time"),
    ("linear", "brunone", "time"),
])
def test_each_friction_law(tmp_path, capsys, friction, unsteady, model):
    extra = ["--friction", friction] + (["--friction-unsteady", unsteady] if unsteady else [])
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
