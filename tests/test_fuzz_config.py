"""Property-based tests of the config loaders: rig, material, bench, device profiles, sim config.

Each built-in config is mutated at random (values of any type, deleted and added keys,
tables and scalars swapped) and loaded: the only acceptable failure is the loader's
one-line error (ConfigError / ProfileError) naming the file; anything else (a
traceback) or a hang fails the test. Accepted configs are checked for sense.
"""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from fuzzing import VALUES, Hang, builtin_doc, dumps, mutated, time_limit
from velab.drivers.base import ProfileError
from velab.errors import ConfigError

pytestmark = pytest.mark.timeout(600)

USER_ERRORS = (ConfigError, ProfileError)
LIMIT_S = 10.0


def load_text(tmp_path, text: str, loader):
    path = tmp_path / "fuzz.toml"
    path.write_text(text, encoding="utf-8")
    try:
        with time_limit(LIMIT_S):
            return loader(path)
    except USER_ERRORS as exc:
        msg = str(exc)
        # a bench's device settings are checked when its driver is built: the error names the device's table
        named = str(path) in msg or msg.startswith(("[devices.", "'")) or "no such device profile" in msg
        assert "\n" not in msg and named, f"not a one-line error naming the file or table: {msg!r}"
        return None
    except Hang:
        pytest.fail(f"loader hung on:\n{text}")


def _rig(path):
    from velab.config import load_rig

    rig = load_rig(path)
    p = rig.pipe
    assert all(math.isfinite(v) and v > 0 for v in (p.length_m, p.inner_diameter_m, p.wall_thickness_m,
                                                   rig.steady_flow_m3_s, rig.nominal_wave_speed_m_s))
    assert p.wall_thickness_m < p.inner_diameter_m / 2
    assert math.isfinite(rig.steady_head_m) and rig.steady_head_m > 0
    return rig


def _material(path):
    from velab.config import load_material

    m = load_material(path)
    assert math.isfinite(m.wave_speed_m_s) and m.wave_speed_m_s > 0
    assert all(e.E_pa > 0 and e.eta_pa_s > 0 and math.isfinite(e.tau_s) for e in m.elements)
    return m


def _modbus_profile(path):
    from velab.drivers.profile import load_profile

    prof = load_profile(path)
    for r in prof.registers.values():
        assert 0 <= r.address <= 0xFFFF and r.scale != 0
    return prof


def _streaming_profile(path):
    from velab.drivers.streaming_adc import load_profile

    return load_profile(path)


def _bench(path):
    from velab.drivers.bench import load_bench, open_device

    bench = load_bench(path)
    for dev in bench.devices.values():
        drv = open_device(dev, connect=False)  # builds bus + driver from the settings; no I/O
        close = getattr(drv, "close", None)
        if close is not None:
            close()
    return bench


def _sim(path):
    from velab.simulators.bench import SimulatedBench

    sim = SimulatedBench.from_config(path, ephemeral=True)  # constructed, never started: nothing bound
    sim.stop()
    return sim


CASES = [
    ("rigs", "perugia", _rig),
    ("materials", "A", _material),
    ("materials", "hdpe_s1", _material),
    ("devices", "modbus_adc", _modbus_profile),
    ("devices", "sitrans_mag6000", _modbus_profile),
    ("devices", "valve_actuator", _modbus_profile),
    ("devices", "streaming_adc", _streaming_profile),
    ("benches", "sim", _bench),
    ("sim", "default", _sim),
]


@pytest.mark.parametrize("kind,name,loader", CASES, ids=[f"{k}-{n}" for k, n, _ in CASES])
def test_builtin_config_loads(kind, name, loader):
    from velab.configpath import find_config

    assert loader(find_config(kind, name)) is not None


@pytest.mark.parametrize("kind,name,loader", CASES, ids=[f"{k}-{n}" for k, n, _ in CASES])
def test_mutated_configs_load_or_fail_in_one_line(kind, name, loader, tmp_path):
    base = builtin_doc(kind, name)

    @given(doc=mutated(base))
    def check(doc):
        load_text(tmp_path, dumps(doc), loader)

    check()


@given(doc=st.dictionaries(st.text(max_size=8), VALUES, max_size=6), kind=st.sampled_from(CASES))
def test_random_documents_fail_in_one_line(doc, kind, tmp_path_factory):
    load_text(tmp_path_factory.mktemp("fz"), dumps(doc), kind[2])


@given(data=st.binary(max_size=300), kind=st.sampled_from(CASES))
def test_random_bytes_fail_in_one_line(data, kind, tmp_path_factory):
    path = tmp_path_factory.mktemp("fz") / "bytes.toml"
    path.write_bytes(data)
    try:
        with time_limit(LIMIT_S):
            kind[2](path)
    except USER_ERRORS as exc:
        assert "\n" not in str(exc)


@pytest.mark.parametrize("kind,name,loader", CASES, ids=[f"{k}-{n}" for k, n, _ in CASES])
def test_special_files_are_refused_before_reading(kind, name, loader, tmp_path):
    import os

    fifo = tmp_path / "fifo.toml"
    os.mkfifo(fifo)  # opening it would block forever
    big = tmp_path / "big.toml"
    big.write_bytes(b"# " + b"x" * (2 << 20) + b"\n")
    for path, reason in (("/dev/zero", "not a regular file"), (fifo, "not a regular file"),
                         (tmp_path, "is a directory"), (big, "larger than"), (tmp_path / "no.toml", "no such file")):
        with time_limit(LIMIT_S), pytest.raises(USER_ERRORS, match=reason):
            loader(path)
