"""The one config lookup: explicit path > $VELAB_CONFIG_PATH > the user's XDG folder > built-in."""

from __future__ import annotations

import os

import pytest

from velab.config import load_material, load_rig
from velab.configpath import builtin_configs, find_config, known_configs, user_config_dir
from velab.drivers.bench import load_bench
from velab.drivers.profile import load_profile
from velab.errors import ConfigError
from velab.simulators.bench import load_sim_config

MATERIAL = 'name = "{name}"\nwave_speed_m_s = {a}\n'


def put(root, kind, name, text):
    d = root / kind
    d.mkdir(parents=True, exist_ok=True)
    (d / f"{name}.toml").write_text(text)
    return d / f"{name}.toml"


@pytest.fixture()
def folders(tmp_path, monkeypatch):
    lab1, lab2, xdg = tmp_path / "lab1", tmp_path / "lab2", tmp_path / "xdg"
    monkeypatch.setenv("VELAB_CONFIG_PATH", os.pathsep.join([str(lab1), "", str(lab2)]))
    monkeypatch.setenv("XDG_CONFIG_HOME", str(xdg))
    return lab1, lab2, xdg / "velab"


def test_builtin_configs_are_package_data():
    root = builtin_configs()
    assert (root / "rigs" / "perugia.toml").is_file()
    assert "velab" in str(root) or "configs" in str(root)
    for kind, name in (("rigs", "perugia"), ("materials", "A"), ("benches", "sim"), ("devices", "modbus_adc"),
                       ("sim", "default")):
        assert name in known_configs(kind)


def test_lookup_order(folders, tmp_path):
    lab1, lab2, user = folders
    assert load_material("A").wave_speed_m_s == pytest.approx(353.73)  # built-in
    put(user, "materials", "A", MATERIAL.format(name="user A", a=300))
    assert load_material("A").name == "user A"                         # user folder hides built-in
    put(lab2, "materials", "A", MATERIAL.format(name="lab2 A", a=310))
    assert load_material("A").name == "lab2 A"                         # $VELAB_CONFIG_PATH first
    put(lab1, "materials", "A", MATERIAL.format(name="lab1 A", a=320))
    assert load_material("A").name == "lab1 A"                         # in its order
    explicit = put(tmp_path / "elsewhere", "materials", "A", MATERIAL.format(name="explicit", a=330))
    assert load_material(explicit).name == "explicit"                   # a path is used as given
    assert load_material(str(explicit)).name == "explicit"
    assert "A" in known_configs("materials")


def test_every_kind_uses_the_same_lookup(folders):
    lab1, _, _ = folders
    put(lab1, "rigs", "hall2", (builtin_configs() / "rigs" / "perugia.toml").read_text().replace(
        'name = "', 'name = "hall2 ', 1))
    assert load_rig("hall2").name.startswith("hall2")
    put(lab1, "devices", "my_adc", (builtin_configs() / "devices" / "modbus_adc.toml").read_text())
    assert load_profile("my_adc").kind == "modbus_adc"
    put(lab1, "benches", "mine", (builtin_configs() / "benches" / "sim.toml").read_text())
    assert set(load_bench("mine").devices) == set(load_bench("sim").devices)
    put(lab1, "sim", "mine", (builtin_configs() / "sim" / "default.toml").read_text())
    assert str(load_sim_config("mine")[0]).startswith(str(lab1))


def test_unknown_name_lists_what_exists(folders):
    lab1, _, _ = folders
    put(lab1, "rigs", "hall2", "")
    with pytest.raises(ConfigError) as exc:
        find_config("rigs", "nosuch")
    msg = str(exc.value)
    assert "\n" not in msg and "hall2" in msg and "perugia" in msg and "VELAB_CONFIG_PATH" in msg


@pytest.mark.parametrize("name", ["", "..", ".hidden", "a b", "x\0y", "-rf"])
def test_names_that_are_not_names(name, folders):
    with pytest.raises(ConfigError):
        find_config("rigs", name)


def test_user_dir_follows_xdg(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path))
    assert user_config_dir() == tmp_path / "velab"
    monkeypatch.setenv("XDG_CONFIG_HOME", "relative/dir")  # ignored, per the XDG spec
    assert user_config_dir() == __import__("pathlib").Path(os.path.expanduser("~")) / ".config" / "velab"


def test_unreadable_lab_folder_does_not_hide_builtins(folders):
    lab1, _, _ = folders
    lab1.mkdir()
    (lab1 / "rigs").write_text("not a folder")
    assert load_rig("perugia").name
