"""Result types of a calibration sweep, and the information criteria (physics.md section 7)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from velab.config import KelvinVoigt, Material
from velab.fitting.engine import dot


def support_category(delta_aic: float) -> str:
    """Burnham & Anderson's rule of thumb for the support of a model given its delta AIC.

    0-2 substantial; 4-7 considerably less; > 10 essentially none. The gaps of the
    rule are named "moderate" (2-4) and "little" (7-10).
    """
    if delta_aic <= 2:
        return "substantial"
    if delta_aic <= 4:
        return "moderate"
    if delta_aic <= 7:
        return "considerably less"
    if delta_aic <= 10:
        return "little"
    return "essentially none"


def model_name(m: int, reduced: bool = False) -> str:
    if m == 0:
        return "EL"
    return f"S{m}r" if reduced else f"S{m}"


@dataclass
class ModelFit:
    """The calibrated parameters and the fit statistics of one model."""

    name: str  # "EL", "S1".."S6"; reduced models "S1r".."S5r"
    m: int  # number of Kelvin-Voigt elements
    k: int  # number of calibrated parameters (2m+1, or m+1 if reduced)
    reduced: bool
    n: int
    F: float  # RSS / n (m^2)
    wave_speed_m_s: float
    E_pa: tuple[float, ...]
    eta_pa_s: tuple[float, ...]
    lag1_autocorr: float  # lag-1 autocorrelation of the residuals
    evaluations: int = 0  # head-model evaluations (Jacobians counted once each)
    jacobians: int = 0
    starts: int = 0
    aic: float = math.nan
    aicc: float = math.nan
    bic: float = math.nan
    delta_aic: float = math.nan
    weight: float = math.nan
    support: str = ""

    @property
    def rss(self) -> float:
        return self.F * self.n

    @property
    def tau_s(self) -> tuple[float, ...]:
        return tuple(h / e for e, h in zip(self.E_pa, self.eta_pa_s))

    @property
    def J_per_pa(self) -> tuple[float, ...]:
        return tuple(1.0 / e for e in self.E_pa)

    def material(self) -> Material:
        return Material(
            wave_speed_m_s=self.wave_speed_m_s,
            elements=tuple(KelvinVoigt(e, h) for e, h in zip(self.E_pa, self.eta_pa_s)),
            name=self.name,
        )

    def elements(self) -> list[dict]:
        return [
            {"E": e, "eta": h, "tau": h / e, "J": 1.0 / e} for e, h in zip(self.E_pa, self.eta_pa_s)
        ]

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "m": self.m,
            "k": self.k,
            "reduced": self.reduced,
            "F": self.F,
            "rss": self.rss,
            "aic": self.aic,
            "aicc": self.aicc,
            "bic": self.bic,
            "delta_aic": self.delta_aic,
            "weight": self.weight,
            "support": self.support,
            "wave_speed": self.wave_speed_m_s,
            "elements": self.elements(),
            "lag1_autocorr": self.lag1_autocorr,
            "evaluations": self.evaluations,
            "jacobians": self.jacobians,
            "starts": self.starts,
        }


def apply_criteria(fits: list[ModelFit]) -> None:
    """Fill AIC, AICc, BIC, delta AIC, Akaike weights and support categories in place."""
    for f in fits:
        nlf = f.n * math.log(f.F) if f.F > 0 else -math.inf
        f.aic = nlf + 2 * f.k
        f.aicc = f.aic + (2 * f.k * (f.k + 1) / (f.n - f.k - 1) if f.n - f.k - 1 > 0 else math.inf)
        f.bic = nlf + f.k * math.log(f.n)
    if not fits:
        return
    best = min(f.aic for f in fits)
    rel = np.array([math.exp(-(f.aic - best) / 2) for f in fits])
    w = rel / rel.sum()
    for f, wi in zip(fits, w):
        f.delta_aic = f.aic - best
        f.weight = float(wi)
        f.support = support_category(f.delta_aic)


@dataclass
class SweepResult:
    """All models calibrated on one record window, ranked by AIC."""

    n: int
    window_s: float
    sample_rate_hz: float
    method: str
    settings: dict
    models: list[ModelFit]
    duration_s: float = 0.0
    evaluations: int = 0  # head-model evaluations over the whole sweep
    notes: list[str] = field(default_factory=list)

    @property
    def best(self) -> ModelFit:
        return min(self.models, key=lambda f: f.aic)

    def __getitem__(self, name: str) -> ModelFit:
        for f in self.models:
            if f.name == name:
                return f
        raise KeyError(name)

    def get(self, name: str) -> ModelFit | None:
        try:
            return self[name]
        except KeyError:
            return None

    def to_dict(self) -> dict:
        return {
            "n": self.n,
            "window": self.window_s,
            "sample_rate_hz": self.sample_rate_hz,
            "method": self.method,
            "settings": self.settings,
            "best": self.best.name,
            "duration_s": self.duration_s,
            "evaluations": self.evaluations,
            "models": [f.to_dict() for f in self.models],
            "notes": list(self.notes),
        }

    def report(self, elements: bool = True) -> str:
        """A plain-text table (one line per model), then the parameters per element."""
        lines = [
            f"n = {self.n} samples, window = {self.window_s:g} s from the trigger "
            f"({self.sample_rate_hz:g} Hz), method = {self.method}",
            f"{'model':<6}{'k':>3}{'F (m^2)':>13}{'AIC':>13}{'AICc':>13}{'BIC':>13}{'dAIC':>10}"
            f"{'weight':>8}  {'support':<18}{'a (m/s)':>9}{'lag1':>7}",
        ]
        best = self.best.name
        for f in self.models:
            mark = "*" if f.name == best else " "
            lines.append(
                f"{f.name + mark:<6}{f.k:>3}{f.F:>13.6e}{f.aic:>13.2f}{f.aicc:>13.2f}{f.bic:>13.2f}"
                f"{f.delta_aic:>10.2f}{f.weight:>8.3f}  {f.support:<18}{f.wave_speed_m_s:>9.2f}"
                f"{f.lag1_autocorr:>7.3f}"
            )
        lines.append(f"best model (minimum AIC): {best}")
        if elements:
            lines.append("")
            lines.append(f"{'model':<6}{'#':>2}{'E (Pa)':>12}{'eta (Pa s)':>12}{'tau (s)':>11}{'J (1/Pa)':>12}")
            for f in self.models:
                for i, el in enumerate(f.elements(), 1):
                    lines.append(
                        f"{f.name:<6}{i:>2}{el['E']:>12.4e}{el['eta']:>12.4e}{el['tau']:>11.4g}{el['J']:>12.4e}"
                    )
        lag = self.best.lag1_autocorr
        lines.append("")
        lines.append(
            f"caveat: AIC assumes independent Gaussian residuals (n = {self.n}); lag-1 autocorrelation of the "
            f"best model's residuals {lag:.2f}"
            + (" -- correlated: AIC over-rewards extra parameters" if abs(lag) > 0.2 else "")
        )
        lines.extend(self.notes)
        return "\n".join(lines)


def lag1(res: np.ndarray) -> float:
    r = np.asarray(res, dtype=float) - np.mean(res)
    d = dot(r, r)
    return float(dot(r[1:], r[:-1]) / d) if d > 0 else 0.0


__all__ = ["ModelFit", "SweepResult", "apply_criteria", "support_category", "model_name", "lag1", "asdict"]
