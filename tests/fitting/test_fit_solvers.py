"""velab.fitting.solvers.levenberg_marquardt: the bounded LM, with a full Jacobian at every step and
with Broyden's update between Jacobians (the time-domain polish and the closure's refinement)."""

import numpy as np

from velab.fitting.solvers import levenberg_marquardt

LO, HI = np.array([0.1, 0.01, 0.5]), np.array([5.0, 5.0, 5.0])  # the box of the damped oscillation's parameters


def _problem(seed=3):
    """A damped oscillation (three nonlinear parameters), noisy: the shape of a head record."""
    t = np.linspace(0.0, 4.0, 800)
    true = np.array([1.2, 0.7, 2.0])  # amplitude, decay rate, angular frequency

    def model(x):
        return x[0] * np.exp(-x[1] * t) * np.cos(x[2] * t)

    d = model(true) + np.random.default_rng(seed).normal(0.0, 0.01, t.size)
    calls = {"jacobian": 0}

    def residual(x):
        return model(x) - d

    def jacobian(x):
        calls["jacobian"] += 1
        e = np.exp(-x[1] * t)
        return np.column_stack([e * np.cos(x[2] * t), -x[0] * t * e * np.cos(x[2] * t),
                                -x[0] * e * t * np.sin(x[2] * t)])

    return residual, jacobian, calls, true


def test_broyden_reaches_the_full_jacobians_optimum_with_fewer_jacobians():
    x0 = np.array([1.1, 0.75, 1.97])  # near the optimum, as the polish starts
    res, jac, calls, true = _problem()
    full = levenberg_marquardt(res, jac, x0, LO, HI, max_iter=40, ftol=1e-12)
    n_full = calls["jacobian"]
    res, jac, calls, _ = _problem()
    quasi = levenberg_marquardt(res, jac, x0, LO, HI, max_iter=40, ftol=1e-12, broyden=True)
    n_quasi = calls["jacobian"]
    F_full, F_quasi = np.sum(full.fun ** 2), np.sum(quasi.fun ** 2)
    assert F_quasi <= F_full * (1 + 1e-6)
    assert np.allclose(quasi.x, full.x, rtol=1e-4)
    assert np.allclose(full.x, true, rtol=0.05)
    assert n_quasi < n_full


def test_broyden_recomputes_the_jacobian_when_its_update_stops_predicting():
    """From far away the updated Jacobian goes stale: the solver must compute it again, not stop."""
    res, jac, calls, true = _problem()
    sol = levenberg_marquardt(res, jac, np.array([0.5, 0.3, 1.6]), LO, HI, max_iter=200, ftol=1e-12, broyden=True)
    assert calls["jacobian"] > 1
    assert np.allclose(sol.x, true, rtol=0.05)


def test_the_box_holds():
    res, jac, _, _ = _problem()
    lo, hi = np.array([0.1, 0.9, 0.5]), np.array([5.0, 5.0, 5.0])  # decay rate bounded above the truth
    for broyden in (False, True):
        sol = levenberg_marquardt(res, jac, np.array([1.0, 1.0, 2.0]), lo, hi, broyden=broyden)
        assert np.all(sol.x >= lo) and np.all(sol.x <= hi)
        assert sol.x[1] == 0.9  # on the bound the data push it to


def _counting(res):
    calls = {"residual": 0}

    def counted(x):
        calls["residual"] += 1
        return res(x)

    return counted, calls


def _finite_differences(res, step=1e-5):
    """The Jacobian by forward differences, as the polish takes it (one model run per parameter)."""
    def jac(x):
        r0 = res(x)
        cols = []
        for i in range(x.size):
            xp = np.array(x, dtype=float)
            xp[i] += step
            cols.append((res(xp) - r0) / step)
        return np.array(cols).T
    return jac


def _optimum():
    res, jac, _, _ = _problem()
    sol = levenberg_marquardt(res, jac, np.array([1.1, 0.75, 1.97]), LO, HI, max_iter=100, ftol=1e-15)
    return sol.x, float(np.sum(sol.fun ** 2))


def test_a_start_at_the_optimum_costs_no_trial_steps_when_the_gain_is_predicted():
    """At the optimum, with a finite-difference Jacobian, every step fails; without the prediction the solver
    tries ever shorter ones (one residual each: a run of the time-domain model in the polish)."""
    x_opt, _ = _optimum()
    res, _, _, _ = _problem()
    fd = _finite_differences(res)
    blind, n_blind = _counting(res)
    levenberg_marquardt(blind, fd, x_opt, LO, HI, ftol=1e-6, broyden=True)
    seeing, n_seeing = _counting(res)
    sol = levenberg_marquardt(seeing, fd, x_opt, LO, HI, ftol=1e-6, broyden=True, predicted=True)
    assert n_blind["residual"] > 5  # (what the prediction saves)
    assert n_seeing["residual"] == 1  # the start's residual only
    np.testing.assert_array_equal(sol.x, x_opt)


def test_the_prediction_stops_no_solve_short_of_its_tolerance():
    """From a start away from the optimum the predicted-gain stop ends at the optimum to within its tolerance
    in F, with a fresh Jacobian at every step and with Broyden's update (whose stale estimate, when it
    predicts no gain, is computed again rather than taken for convergence)."""
    _, F_opt = _optimum()
    for broyden in (False, True):
        res, jac, _, true = _problem()
        sol = levenberg_marquardt(res, jac, np.array([0.9, 0.5, 1.8]), LO, HI, max_iter=200, ftol=1e-6,
                                  broyden=broyden, predicted=True)
        assert F_opt <= np.sum(sol.fun ** 2) <= F_opt * (1 + 2e-6), broyden
        assert np.allclose(sol.x, true, rtol=0.05)
