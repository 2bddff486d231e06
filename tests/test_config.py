"""Rig and material configuration: typed objects, one-line errors naming file and key."""

import math

import pytest

from velab.cli import main
from velab.config import KelvinVoigt, load_material, load_rig
from velab.rig import constraint_coefficient
from velab.errors import ConfigError

RIG = """
name = "test rig"
[pipe]
length_m = 100.0
inner_diameter_m = 0.1
wall_thickness_m = 0.005
constraint_alpha = 1.0
pressure_rating_bar = 10
[flow]
steady_flow_m3_s = 0.003
reservoir_head_m = 30
[manoeuvre]
beta_per_s = 32
gamma = -5.5
[transducer]
full_scale_bar = 6
[wave]
nominal_speed_m_s = 350
"""


def write(tmp_path, text, name="rig.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_reference_rig_matches_physics_md():
    rig = load_rig("perugia")
    assert rig.pipe.length_m == 102.58
    assert rig.pipe.inner_diameter_m == 0.0968
    assert rig.steady_flow_m3_s == 3.64e-3
    # Joukowsky head a Q0 / (g A) about 17.8 m (physics.md section 6)
    assert rig.joukowsky_head_m() == pytest.approx(17.8, abs=0.1)
    # the tangent R doubles the steady head loss at the final level
    assert rig.linear_resistance * rig.pipe.length_m * rig.steady_flow_m3_s == pytest.approx(2 * rig.steady_head_loss_m)
    assert rig.manoeuvre.half_closure_s == pytest.approx(0.172, abs=1e-3)
    assert rig.manoeuvre.closure_time_s == pytest.approx(0.137, abs=1e-3)
    assert rig.transducer.full_scale_pa == 6e5
    assert rig.pipe.pressure_rating_pa == 1e6


def test_materials_a_and_b():
    a = load_material("A")
    assert a.model_name == "S3"
    assert [round(e.tau_s, 6) for e in a.elements] == [2.0, 0.2, 0.02]
    b = load_material("B")
    assert [round(e.tau_s, 6) for e in b.elements] == [0.02, 0.2, 2.0]
    assert load_material("elastic").model_name == "EL"


def test_material_from_creep_form(tmp_path):
    p = write(tmp_path, 'wave_speed_m_s = 300\n[[kelvin_voigt]]\nJ_per_pa = 2e-10\ntau_s = 0.5\n', "m.toml")
    m = load_material(p)
    assert m.elements[0].E_pa == pytest.approx(5e9)
    assert m.elements[0].tau_s == pytest.approx(0.5)
    assert KelvinVoigt.from_creep(2e-10, 0.5) == m.elements[0]


def test_frozen():
    rig = load_rig("perugia")
    with pytest.raises(Exception):
        rig.pipe.length_m = 1.0


def test_constraint_from_anchoring(tmp_path):
    text = RIG.replace("constraint_alpha = 1.0", 'anchoring = "upstream"\npoisson_ratio = 0.46')
    rig = load_rig(write(tmp_path, text))
    assert rig.pipe.constraint_alpha == pytest.approx(1 - 0.46 / 2)
    thick = constraint_coefficient("throughout", 0.46, 0.1, 0.005, thick=True)
    assert thick == pytest.approx(2 * 0.05 * 1.46 + 0.1 * (1 - 0.46**2) / 0.105)


@pytest.mark.parametrize(
    "change, where, reason",
    [
        (("wall_thickness_m = 0.005", "wall_thickness_m = 0.06"), "[pipe] wall_thickness_m", "less than half"),
        (("length_m = 100.0", "length_m = -1.0"), "[pipe] length_m", "must be positive"),
        (("length_m = 100.0", 'length_m = "long"'), "[pipe] length_m", "must be a number"),
        (("gamma = -5.5", "gamma = -5.5\ngama = 1"), "[manoeuvre] gama", "unknown key"),
        (("[wave]\nnominal_speed_m_s = 350", ""), "[wave]", "missing table"),
        (("beta_per_s = 32\n", ""), "[manoeuvre] beta_per_s", "missing key"),
        (("constraint_alpha = 1.0", "constraint_alpha = 1.0\nanchoring = \"upstream\""), "[pipe] anchoring", "not both"),
    ],
)
def test_rig_errors_name_file_key_reason(tmp_path, change, where, reason):
    p = write(tmp_path, RIG.replace(*change))
    with pytest.raises(ConfigError) as exc:
        load_rig(p)
    msg = str(exc.value)
    assert str(p) in msg and where in msg and reason in msg
    assert "\n" not in msg


def test_bad_toml_and_missing_file(tmp_path):
    p = write(tmp_path, "[pipe\nlength_m = 1")
    with pytest.raises(ConfigError, match="invalid TOML"):
        load_rig(p)
    with pytest.raises(ConfigError, match="no such file"):
        load_rig(tmp_path / "nope.toml")
    with pytest.raises(ConfigError, match="built-in: .*perugia"):
        load_rig("nosuchrig")


def test_material_errors(tmp_path):
    p = write(tmp_path, 'wave_speed_m_s = 300\n[[kelvin_voigt]]\nE_pa = 1e9\ntau_s = 0.5\n', "m.toml")
    with pytest.raises(ConfigError, match=r"kelvin_voigt\]\] #1.*either E_pa \+ eta_pa_s or J_per_pa \+ tau_s"):
        load_material(p)
    p = write(tmp_path, 'wave_speed_m_s = 300\n[[kelvin_voigt]]\nE_pa = -1e9\neta_pa_s = 1\n', "m2.toml")
    with pytest.raises(ConfigError, match="E_pa: must be positive"):
        load_material(p)


def test_cli_config_error_is_one_line(tmp_path, capsys):
    p = write(tmp_path, RIG.replace("length_m = 100.0", "length_m = 0"))
    rc = main(["synth", "--rig", str(p), "-o", str(tmp_path / "x.h5")])
    err = capsys.readouterr().err
    assert rc != 0
    assert err.count("\n") == 1 and "length_m" in err and "Traceback" not in err
    assert not (tmp_path / "x.h5").exists()


@pytest.mark.parametrize("argv", [["synth", "--rate", "abc", "-o", "x.h5"], ["nosuchcommand"], ["fit"],
                                  ["record", "--simulate", "--duration", "-3"], ["import", "x.csv"]])
def test_bad_arguments_one_line(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    err = capsys.readouterr().err
    assert exc.value.code == 2
    assert err.count("\n") == 1 and err.startswith("velab") and "--help" in err


def test_valve_table_default_and_given(tmp_path):
    """No [valve] table: the butterfly on the orifice law; a given table is read as written."""
    v = load_rig(write(tmp_path, RIG)).valve
    assert (v.law, v.characteristic, v.series_loss_share) == ("orifice", "butterfly", 0.05)
    text = RIG + '[valve]\ncharacteristic = "table"\nposition_pct = [0, 50, 100]\nflow_ratio = [0, 0.3, 1]\n'
    v = load_rig(write(tmp_path, text, "t.toml")).valve
    assert v.characteristic == "table" and v.position_pct == (0.0, 50.0, 100.0) and v.flow_ratio == (0.0, 0.3, 1.0)
    v = load_rig(write(tmp_path, RIG + '[valve]\nlaw = "imposed"\n', "i.toml")).valve
    assert v.law == "imposed"


@pytest.mark.parametrize(
    "table, where, reason",
    [
        ('law = "sigmoid"', "[valve] law", "orifice"),
        ('characteristic = "globe"', "[valve] characteristic", "butterfly"),
        ("series_loss_share = 0", "[valve] series_loss_share", "must be in (0, 1]"),
        ("series_loss_share = 1.5", "[valve] series_loss_share", "must be in (0, 1]"),
        ('characteristic = "power"', "[valve] exponent", "missing key"),
        ("exponent = 2.5", "[valve] exponent", 'only used with characteristic = "power"'),
        ('characteristic = "power"\nexponent = -1', "[valve] exponent", "must be positive"),
        ('characteristic = "table"\nposition_pct = [0, 100]', "[valve] flow_ratio", "missing key"),
        ('characteristic = "table"\nposition_pct = [0, 60, 50, 100]\nflow_ratio = [0, 0.2, 0.5, 1]',
         "[valve] position_pct", "increase strictly"),
        ('characteristic = "table"\nposition_pct = [0, 100]\nflow_ratio = [0, "x"]', "[valve] flow_ratio",
         "finite numbers"),
        ("position_pct = [0, 100]", "[valve] position_pct", 'only used with characteristic = "table"'),
        ("opening = 1", "[valve] opening", "unknown key"),
    ],
)
def test_valve_errors_name_file_key_reason(tmp_path, table, where, reason):
    p = write(tmp_path, RIG + "[valve]\n" + table + "\n")
    with pytest.raises(ConfigError) as exc:
        load_rig(p)
    msg = str(exc.value)
    assert str(p) in msg and where in msg and reason in msg, msg
    assert "\n" not in msg
