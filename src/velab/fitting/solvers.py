"""Local and global solvers on one objective F(x) = |h(x) - d|^2 / n (one grid, one data vector)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from velab.fitting.engine import HeadEvaluator, dot, gram, sumsq
from velab.fitting.offset import objective, project_gram
from velab.fitting.params import ParamMap


# the stall test of Stage.lsq: the gain over this many evaluations
STALL_EVALS = 10
# one variable (EL: ln a) is solved by a safeguarded secant on dF/dx (Stage.lsq_1d): Gauss-Newton
# converges only linearly when the residual is large (EL's F is 10^5 times the noise), at about 9 %
# of the remaining distance per step on the reference records, and stopped 40 evaluations short.
# (A switch for benchmarks/fit_sweep.py's "previous sweep".)
SECANT_1D = True
# its tolerance on the variable: ln a to 1e-10 is a to 0.04 micrometres per second
XTOL_1D = 1e-10


# the simplex's evaluations for one model's search or polish (method "nelder-mead": the single sweep's and the
# stacked one's)
NELDER_MEAD_MAXFEV = 1000


@dataclass
class Sol:
    x: np.ndarray
    F: float
    pm: ParamMap


class Stage:
    """One objective: an evaluator on a grid and the data on that grid.

    ``baseline``: the baseline's sample count on this grid (or, stacked, its blocks: velab.fitting.offset);
    the steady head's offset is then fitted with every model, the baseline its prior; 0: the steady head
    as the data have it.
    """

    def __init__(self, ev: HeadEvaluator, d: np.ndarray, baseline=0.0):
        self.ev = ev
        self.d = d
        self.baseline = baseline

    def with_data(self, d: np.ndarray) -> "Stage":
        """Same evaluator, other data (e.g. corrected for the friction nonlinearity)."""
        return Stage(self.ev, d, self.baseline)

    def on(self, ev: HeadEvaluator) -> "Stage":
        """Same data (and baseline), another evaluator of the same grid."""
        return Stage(ev, self.d, self.baseline)

    def F(self, pm: ParamMap, x) -> float:
        r = self.ev.head(*pm.unpack(x)) - self.d
        return objective(r, self.baseline) / self.d.size

    def sol(self, pm: ParamMap, x) -> Sol:
        x = pm.project(x)
        return Sol(x, self.F(pm, x), pm)

    def lsq(self, pm: ParamMap, x0, *, max_nfev: int, ftol: float, stall: tuple[int, float] | None = None,
            secant: bool = True) -> Sol:
        """Bounded Levenberg-Marquardt on F with the analytic Jacobian (normal equations).

        The Jacobian has n rows but only k <= 13 columns: working with the k x k
        matrix J^T J (column-scaled, Marquardt damping) costs far less than a
        factorisation of J itself. Bounds: variables at a bound whose gradient points
        outward are frozen; steps are projected on the box. Damping: Nielsen's update
        from the gain ratio (actual over predicted decrease), which avoids the
        accept/reject zig-zag of a fixed up/down factor along the J-tau ridge.

        The residual and the Jacobian are kept as 1 + k rows of length n (C order), so
        one Gram product [r; J] [r; J]^T gives J^T r and J^T J; the current and the
        trial point live in two buffers that are swapped on acceptance. The result is
        never worse than the start (only steps that lower F are accepted).

        ``stall = (n_aic, gain)``: also stop when the last STALL_EVALS evaluations together lowered
        n_aic ln F by less than ``gain`` (the crawl along the flat J-tau ridge no longer changes
        the AIC at the precision it is reported to).

        One variable (``secant`` and SECANT_1D): :meth:`lsq_1d` instead.
        """
        if SECANT_1D and secant and pm.size == 1:
            return self.lsq_1d(pm, x0, max_nfev=max_nfev)
        x = pm.project(x0)
        n = self.d.size
        ev = self.ev
        tau_free = pm.tau_free
        k = pm.size
        bufs = (np.empty((1 + k, ev.n_t)), np.empty((1 + k, ev.n_t)))
        cur = 0

        def evaluate(i, xe):
            b = bufs[i]
            ev.head_jac_x(*pm.unpack(xe), tau_free, out=b)
            b[0] -= self.d  # row 0: residual
            return objective(b[0], self.baseline) / n

        F = evaluate(cur, x)
        history = [F]  # F after each evaluation (the stall test)
        lam = 1e-3
        nu = 2.0
        nfev = 1
        lo, hi = pm.bounds()
        while nfev < max_nfev:
            M = project_gram(gram(bufs[cur]), bufs[cur], self.baseline)
            g = M[1:, 0]
            A = M[1:, 1:]
            free = ~(((x <= lo + 1e-12) & (g > 0)) | ((x >= hi - 1e-12) & (g < 0)))
            if not free.any():
                break
            if free.all():
                Af, gf = A, g
            else:
                Af = A[np.ix_(free, free)]
                gf = g[free]
            dscale = np.sqrt(np.maximum(np.diag(Af), 1e-300))
            As = Af / np.outer(dscale, dscale)
            gs = gf / dscale
            eye = np.eye(As.shape[0])
            improved = False
            while nfev < max_nfev:
                try:
                    step = -np.linalg.solve(As + lam * eye, gs) / dscale
                except np.linalg.LinAlgError:
                    lam *= 10
                    continue
                if not np.all(np.isfinite(step)):
                    lam *= 10
                    if lam > 1e12:
                        break
                    continue
                xt = x.copy()
                xt[free] += np.clip(step, -2.0, 2.0)
                xt = pm.project(xt)
                dx = xt - x
                if not np.any(dx):
                    break
                Ft = evaluate(1 - cur, xt)
                nfev += 1
                if stall is not None:
                    history.append(min(Ft, F))
                    if len(history) > STALL_EVALS and stall[0] * math.log(history[-1 - STALL_EVALS] / max(history[-1], 1e-300)) < stall[1]:
                        if Ft < F:
                            x, F = xt, Ft
                        return Sol(x, F, pm)
                if Ft < F:
                    # predicted decrease of the linear model: -(|r + J dx|^2 - |r|^2)/n
                    pred = predicted_decrease(g, A, dx) / n
                    rel = (F - Ft) / F
                    rho = min(max((F - Ft) / max(pred, 1e-300), 0.0), 2.0)
                    lam = max(lam * max(1 / 3, 1 - (2 * rho - 1) ** 3), 1e-12)
                    nu = 2.0
                    x, F = xt, Ft
                    cur = 1 - cur
                    improved = True
                    if rel < ftol and pred / max(F, 1e-300) < 10 * ftol:
                        return Sol(x, F, pm)
                    break
                lam *= nu
                nu *= 2
                if lam > 1e12:
                    break
            if not improved:
                break
        return Sol(x, F, pm)

    def lsq_1d(self, pm: ParamMap, x0, *, max_nfev: int, xtol: float = XTOL_1D) -> Sol:
        """One variable: safeguarded secant on the gradient g = J.r (never worse than the start).

        The first step is Gauss-Newton's (-J.r / J.J); then the secant through the last two
        gradients gives the curvature, including the residual's own second derivative that
        Gauss-Newton leaves out (large on a large residual). The minimum is kept bracketed: a
        gradient sign or a rise of F bounds it, and a step that leaves the bracket bisects it.
        """
        n = self.d.size
        buf = np.empty((2, self.ev.n_t))
        lo, hi = (float(v[0]) for v in pm.bounds())

        def evaluate(xe: float):
            self.ev.head_jac_x(*pm.unpack(np.array([xe])), pm.tau_free, out=buf)
            buf[0] -= self.d
            if self.baseline:  # the offset projected out (velab.fitting.offset)
                M = project_gram(gram(buf), buf, self.baseline)
                return objective(buf[0], self.baseline) / n, float(M[1, 0]), float(M[1, 1])
            return sumsq(buf[0]) / n, dot(buf[1], buf[0]), dot(buf[1], buf[1])

        x = float(pm.project(x0)[0])
        F, g, c = evaluate(x)
        nfev = 1
        left, right = lo, hi  # the minimum next to x lies in [left, right]
        other: tuple[float, float] | None = None  # (x, g) of the last other point: the secant
        while nfev < max_nfev and g != 0.0:
            if g > 0:
                right = min(right, x)
            else:
                left = max(left, x)
            curv = (g - other[1]) / (x - other[0]) if other is not None and other[0] != x else 0.0
            step = -g / curv if curv > 0 else -g / max(c, 1e-300)
            step = min(max(step, -2.0), 2.0)
            xt = x + step
            if not left < xt < right:
                xt = 0.5 * (x + (right if step > 0 else left))
            if abs(xt - x) <= xtol:
                break
            Ft, gt, ct = evaluate(xt)
            nfev += 1
            if Ft < F:
                other = (x, g)
                x, F, g, c = xt, Ft, gt, ct
            else:
                other = (xt, gt)
                if xt > x:
                    right = xt
                else:
                    left = xt
        return Sol(np.array([x]), F, pm)

    def nelder_mead(self, pm: ParamMap, x0, *, maxfev: int = NELDER_MEAD_MAXFEV) -> Sol:
        """The paper's simplex search (tolerance 1e-16 on F), never worse than the start."""
        x0 = pm.project(x0)
        F0 = self.F(pm, x0)

        def f(x):
            return self.F(pm, pm.project(x))

        # the initial simplex must not collapse on a variable at its bound: step inward
        lo, hi = pm.bounds()
        simplex = [x0]
        for i in range(x0.size):
            xi = x0.copy()
            step = 0.05 * max(1.0, abs(x0[i])) if i else 0.02
            xi[i] = x0[i] + step if x0[i] + step <= hi[i] else x0[i] - step
            simplex.append(xi)
        from scipy.optimize import minimize  # (buys start-up time: scipy.optimize only for --method nelder-mead)

        r = minimize(f, x0, method="Nelder-Mead",
                     options={"xatol": 1e-10, "fatol": 1e-16, "maxfev": maxfev, "adaptive": True,
                              "initial_simplex": np.array(simplex)})
        x = pm.project(r.x)
        F = self.F(pm, x)
        return Sol(x, F, pm) if F <= F0 else Sol(x0, F0, pm)

    def evolution(self, pm: ParamMap, seed: int, maxiter: int, x0=None) -> Sol:
        """scipy's differential evolution over the whole box (seeded with ``x0`` if given)."""
        from scipy.optimize import differential_evolution  # (buys start-up time: only for --method evolution)

        lo, hi = pm.bounds()
        r = differential_evolution(
            lambda x: self.F(pm, pm.project(x)), list(zip(lo, hi)), seed=seed, maxiter=maxiter,
            popsize=12, tol=1e-10, polish=False, init="sobol",
            x0=None if x0 is None else pm.project(x0),
        )
        x = pm.project(r.x)
        return Sol(x, self.F(pm, x), pm)


def predicted_decrease(g: np.ndarray, A: np.ndarray, dx: np.ndarray) -> float:
    """|r|^2 - |r + J dx|^2, the decrease of the residual's sum of squares that the linear model predicts for
    the step dx, from g = J^T r and A = J^T J."""
    return -(2.0 * float(g @ dx) + float(dx @ A @ dx))


@dataclass
class LMSolution:
    x: np.ndarray
    fun: np.ndarray
    jac: np.ndarray
    iterations: int


def levenberg_marquardt(residual, jacobian, x0, lo, hi, *, max_iter: int = 40, ftol: float = 1e-7,
                        broyden: bool = False, predicted: bool = False) -> LMSolution:
    """A small bounded Levenberg-Marquardt (steps clipped to the box, Marquardt's diagonal scaling):
    ten parameters and a few thousand residuals, where scipy's trust-region solver spends its time in
    an SVD per iteration.

    ``broyden``: the Jacobian is computed once, at the start, and then carried by Broyden's rank-one
    update along each accepted step (computed again only where a step it predicts fails): for a
    residual whose Jacobian costs one expensive model run per parameter (the time-domain model),
    started near its optimum. The returned ``jac`` is then that updated estimate.

    ``predicted``: a step that the linear model of the residual (the Jacobian) predicts to gain less
    than ``ftol`` of F is not tried: with a Jacobian computed at x the solver has converged (without it,
    a start already at the optimum tries ever shorter steps, one residual each, until the damping reaches
    its ceiling: ~25 runs of an expensive model to learn nothing); with a Broyden estimate the Jacobian
    is computed again first.

    A variable whose bounds coincide is held: its Jacobian column is taken as zero (it neither moves nor
    shares the step with the others, and adds no variance to theirs)."""
    x = np.clip(np.asarray(x0, dtype=float), lo, hi)
    held = np.asarray(lo, dtype=float) >= np.asarray(hi, dtype=float)
    if held.any():
        jacobian = _holding(jacobian, held)
    r = residual(x)
    F = sumsq(r)
    lam = 1e-3
    J = jacobian(x)
    fresh = True  # J is the Jacobian at x (not an update)
    it = 0
    for it in range(1, max_iter + 1):
        # sums over the samples in fixed blocks (velab.fitting.engine): a threaded BLAS would sum in an
        # order that depends on the machine's load, and the fit process must reproduce this one bit for bit
        Jt = np.ascontiguousarray(J.T)
        A = gram(Jt)
        g = np.array([dot(row, r) for row in Jt])
        D = np.maximum(np.diag(A), 1e-30)
        improved = False
        tries = 0
        while lam < 1e12:
            try:
                step = np.linalg.solve(A + lam * np.diag(D), -g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            xn = np.clip(x + step, lo, hi)
            if predicted:
                dx = xn - x
                if predicted_decrease(g, A, dx) < ftol * F:
                    break
            rn = residual(xn)
            Fn = sumsq(rn)
            if Fn < F:
                improved = True
                break
            lam *= 4.0
            tries += 1
            if broyden and not fresh and tries >= 2:
                break  # the updated Jacobian no longer predicts: compute it again here
        if not improved:
            if broyden and not fresh:
                J, fresh = jacobian(x), True
                continue
            break
        gain = (F - Fn) / F
        s = xn - x
        if broyden:
            ss = float(s @ s)
            if ss > 0.0:
                J = J + np.outer((rn - r) - J @ s, s) / ss
            fresh = False
        x, r, F = xn, rn, Fn
        lam = max(lam / 3.0, 1e-12)
        if gain < ftol:
            if not broyden:
                J = jacobian(x)
            break
        if not broyden:
            J = jacobian(x)
    return LMSolution(x, r, J, it)


def _holding(jacobian, held: np.ndarray):
    """``jacobian`` with the columns of the held variables zero."""
    def jac(x):
        J = np.array(jacobian(x), dtype=float)
        J[:, held] = 0.0
        return J
    return jac
