"""velab.complexops: the head model's complex tanh, sqrt and division from real ufuncs agree with numpy's
complex ufuncs to a few units in the last place, on the values the model meets and beyond."""

import numpy as np
import pytest

from velab import complexops


def _work(n):
    return list(np.empty((complexops.WORK, n)))


def _rel(a, b):
    return np.max(np.abs(a - b) / np.abs(b))


def test_tanh_matches_numpy_including_small_large_and_near_pole_arguments():
    rng = np.random.default_rng(1)
    z = rng.uniform(0, 8, 5000) + 1j * rng.uniform(-900, 900, 5000)
    special = [1e-9 + 1e-8j, 1e-3 + 1.5j, 0.1 + np.pi / 2 * 1j, 3 + 0j, 21.9 + 1j, 22.5 + 2j, 700 + 1j, 0 + 0j]
    z = np.concatenate([z, special])
    out = np.empty_like(z)
    got = complexops.tanh(z, out, _work(z.size))
    ref = np.tanh(z)
    ok = ref != 0
    assert _rel(got[ok], ref[ok]) < 4e-15
    assert got[-1] == 0
    assert np.all(np.isfinite(got))


def test_sqrt_is_the_principal_branch_on_every_quadrant_and_scale():
    rng = np.random.default_rng(2)
    n = 6000
    z = rng.normal(size=n) * 10 ** rng.uniform(-12, 12, n) + 1j * rng.normal(size=n) * 10 ** rng.uniform(-12, 12, n)
    z[:4] = [-4 + 0j, 4 + 0j, -1e-300 + 1e-300j, -(1 + 1e-17j)]
    ref = np.sqrt(z)
    got = complexops.sqrt(z.copy(), np.empty_like(z), _work(n), np.empty(n, dtype=bool))
    assert _rel(got, ref) < 4e-16
    assert np.all(got.real >= 0)
    # in place, as the evaluator calls it
    zz = z.copy()
    complexops.sqrt(zz, zz, _work(n), np.empty(n, dtype=bool))
    assert np.array_equal(zz, got)


@pytest.mark.parametrize("in_place", [False, True])
def test_divide_matches_numpy_in_the_models_range(in_place):
    rng = np.random.default_rng(3)
    n = 4000
    p = rng.normal(size=n) * 10 ** rng.uniform(-10, 10, n) + 1j * rng.normal(size=n)
    q = rng.normal(size=n) * 10 ** rng.uniform(-10, 10, n) + 1j * rng.normal(size=n) * 10 ** rng.uniform(-10, 10, n)
    ref = p / q
    out = p.copy() if in_place else np.empty_like(p)
    got = complexops.divide(out if in_place else p, q, out, _work(n))
    assert _rel(got, ref) < 1e-15


def test_the_head_model_is_numpys_to_rounding():
    from velab.config import load_rig
    from velab.model import ValveHeadModel

    rig = load_rig("perugia")
    t = np.arange(-100, 4000) / 1000.0
    vm = ValveHeadModel(rig, t, band_hz=None)
    J, tau = np.array([0.02, 0.05]), np.array([0.01, 0.5])
    fast = vm.head_params(350.0, J, tau)
    old = complexops.ENABLED
    complexops.ENABLED = False
    try:
        ref = vm.head_params(350.0, J, tau)
    finally:
        complexops.ENABLED = old
    assert np.max(np.abs(fast - ref)) < 1e-12 * np.max(np.abs(ref))
