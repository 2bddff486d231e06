"""The reduced family S1r..S5r: its jobs, parameter map and starts, for both sweeps (velab.fitting.sweep's
``fit_sweep`` and velab.fitting.joint.StackedSweep with ``reduced=True``), and the stacked sweep's fit of it.

A reduced model's retardation times are fixed at REDUCED_RETARDATION_TIMES_S[:m], only the wave speed and the
compliances are fitted; the family is fitted after the full one, each model from the one before (S1r from EL),
and guarded by it (it contains it: its last compliance can vanish). Models are keyed (m, reduced) as the single
sweep's jobs, named by velab.fitting.results.model_name(m, reduced).

``fit_reduced`` and ``sweep_reduced`` take a StackedSweep (duck-typed: this module does not import
velab.fitting.joint, which imports it).
"""

from __future__ import annotations

import numpy as np

from velab.config import REDUCED_RETARDATION_TIMES_S
from velab.fitting.params import ParamMap
from velab.fitting.results import model_name
from velab.fitting.starts import cap_starts, coarse_search, continues_by_lsq

MAX_REDUCED = len(REDUCED_RETARDATION_TIMES_S)  # S5r
# the starts' total compliance J'_1 + ... + J'_m spread evenly (``starts``)
TOTALS = (0.1, 0.5)


def jobs(ms, reduced: bool) -> list[tuple[int, bool]]:
    """The models a fit of ``ms`` reports, as fit_sweep orders them: (m, False) for each m, then with ``reduced``
    (m, True) for each m in 1..MAX_REDUCED."""
    out = [(m, False) for m in sorted(ms)]
    if reduced:
        out += [(m, True) for m in sorted(ms) if 1 <= m <= MAX_REDUCED]
    return out


def below(job: tuple[int, bool]) -> tuple[int, bool]:
    """The model ``job`` contains, one element fewer: S(m-1) of its family (S1r's is EL)."""
    m, red = job
    return m - 1, red and m > 1


def param_map(m: int, bounds) -> ParamMap:
    """S(m)r's variables (ln a, ln J'_1..J'_m): tau fixed at the first m of REDUCED_RETARDATION_TIMES_S."""
    return ParamMap(m, bounds, tuple(REDUCED_RETARDATION_TIMES_S[:m]))


def starts(pm: ParamMap, base) -> list[np.ndarray]:
    """S(m)r's coarse starts from ``base`` (S(m-1)r's or EL's solution, a Sol), in both sweeps: the model
    below plus a small element (J' 1e-3), then the nominal totals of TOTALS at the wave speed they stiffen."""
    a = base.pm.unpack(base.x)[0]
    out = [pm.clip(pm.embed(base.pm, base.x, J_new=1e-3))] if base.pm.m else []
    out += [pm.clip(pm.pack(a * (1 + tot) ** 0.5, np.full(pm.m, tot / pm.m))) for tot in TOTALS]
    return out


def fit_reduced(sw, m: int, base):
    """S(m)r on the stacked parts from ``base`` (the model it contains, a joint._Model): the coarse search of
    every part (few starts, few variables: not only the search parts), continued by least squares, polished
    and refreshed as a full model (``sw.polish``), guarded by ``base`` (``sw.nest``). The parts' linear friction
    stand-in is left as the full family left it: it sets how fast the refreshes converge, not where, and the
    full models are then the same with or without the reduced ones."""
    pm = param_map(m, sw.bounds)
    coarse = sw.stage("c", base)
    sols = coarse_search(coarse, pm, cap_starts(starts(pm, base.sol), sw.max_starts), sw.method, sw.seed + m, 60)
    x = sols[0].x
    if continues_by_lsq(sw.method, pm):
        x = coarse.lsq(pm, x, max_nfev=150, ftol=1e-12).x
    return sw.nest(pm, sw.polish(pm, x, base), base)


def sweep_reduced(sw, ms, progress=None) -> None:
    """S1r .. S(top)r into ``sw.final`` (keys (m, True)), top the largest reduced model ``ms`` reports, each from
    the one before; ``progress(done, total, name)`` after each one reported (counted after the full family)."""
    reported = jobs(ms, True)
    top = max((m for m, red in reported if red), default=0)
    base = sw.final[(0, False)]
    for m in range(1, top + 1):
        base = sw.final[(m, True)] = fit_reduced(sw, m, base)
        if progress is not None and (m, True) in reported:
            progress(reported.index((m, True)) + 1, len(reported), model_name(m, True))
