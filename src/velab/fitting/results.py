"""Result types of a calibration: ``ModelFit`` (one model) and ``SweepResult`` (every model of one record
window, ranked), with their JSON form (``to_dict`` / ``from_dict``, tolerant of older documents).

``ModelFit.aic`` is the paper's white-noise AIC, ``aic_ar1`` the AR(1) likelihood's; ``delta_aic``, ``weight``
and ``support`` follow the result's selection criterion, ``SweepResult.best`` its least: all set by
velab.fitting.selection. Results hold numbers, not text: the report is velab.fitting.report's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from velab.config import KelvinVoigt, Material
from velab.fitting.adequacy import bound_message
from velab.fitting.creep import creep_of
from velab.fitting.selection import SELECTIONS, averaged_creep_of, best_of, model_error_elements
from velab.fitting.settings import FitSettings


def model_name(m: int, reduced: bool = False) -> str:
    if m == 0:
        return "EL"
    return f"S{m}r" if reduced else f"S{m}"


def _optional(v) -> float | None:
    """A stored number that may be absent (None: not computed, or a document before it existed)."""
    try:
        v = float(v)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _warnings(v) -> list[dict]:
    """Stored warnings as [{"code", "message"}] (anything else in a damaged document is dropped)."""
    return [{"code": str(w.get("code", "")), "message": str(w.get("message", ""))}
            for w in (v if isinstance(v, list) else []) if isinstance(w, dict)]


def _cov_x(v, m: int, reduced: bool) -> list | None:
    """A stored covariance in x as a square list of lists (null -> NaN: a fixed parameter), or None
    when absent (a fit stored before it was kept) or not the model's size."""
    size = 1 + (m if reduced else 2 * m)
    try:
        C = np.array([[math.nan if x is None else float(x) for x in row] for row in v], dtype=float)
    except (TypeError, ValueError):
        return None
    if C.shape != (size, size):
        return None
    return C.tolist()


def _nan_tuple(v, m):
    v = tuple(float(x) if x is not None else math.nan for x in (v or ()))
    return v if len(v) == m else (math.nan,) * m


@dataclass
class ModelFit:
    """The calibrated parameters and the fit statistics of one model.

    Per-element tuples are sorted by retardation time. Standard errors are NaN where a
    parameter is fixed (on a bound, vanished element, fixed tau of a reduced model).
    """

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
    aic: float = math.nan  # white-noise AIC (the paper's)
    aicc: float = math.nan
    bic: float = math.nan
    delta_aic: float = math.nan  # by the sweep's selection criterion
    weight: float = math.nan
    support: str = ""
    J_rel: tuple[float, ...] = ()  # J'_k = J_k a^2 rho alpha D / e (share of phi(0))
    innovation_var: float = math.nan  # s_e^2 of the AR(1) likelihood (m^2)
    aic_ar1: float = math.nan
    delta_aic_white: float = math.nan
    n_eff: float = math.nan  # effective sample size n (1 - rho) / (1 + rho)
    wave_speed_se_m_s: float = math.nan
    E_se_pa: tuple[float, ...] = ()
    eta_se_pa_s: tuple[float, ...] = ()
    tau_se_s: tuple[float, ...] = ()
    J_rel_se: tuple[float, ...] = ()
    negligible: tuple[bool, ...] = ()  # element vanished (buys < NEGLIGIBLE_GAIN of n ln F)
    element_gain: tuple[float, ...] = ()  # n ln(F without the element / F), others fixed
    at_bounds: list = field(default_factory=list)  # parameters that end on a bound (dicts)
    equivalent_to: str = ""  # "S1" when S2's extra element vanished (or two share tau), else ""
    # the elements (indices, sorted by tau) that only take up a model error, not the wall's creep: set by
    # velab.fitting.selection.mark_model_errors, which then names the model ``equivalent_to`` the smaller one
    model_error_elements: tuple[int, ...] = ()
    split_elements: int = 0  # live elements whose retardation time another one already has
    friction: dict = field(default_factory=dict)  # friction correction of this model (see friction.py)
    noise_ratio: float | None = None  # F / the pretrigger baseline's noise variance (velab.fitting.adequacy)
    # covariance of x = (ln a, ln J'_k[, ln tau_k]) in the elements' order (sorted by tau), inflated by
    # n/n_eff; NaN rows/columns for parameters held fixed; None for fits stored before it was kept.
    # The creep band comes from it (velab.fitting.creep).
    cov_x: list | None = None
    # what the fit added to the baseline's steady head (m): the offset fitted with the model, the baseline
    # its prior (velab.fitting.offset); 0 without a baseline
    steady_head_offset_m: float = 0.0

    @property
    def rss(self) -> float:
        return self.F * self.n

    @property
    def tau_s(self) -> tuple[float, ...]:
        return tuple(h / e for e, h in zip(self.E_pa, self.eta_pa_s))

    @property
    def J_per_pa(self) -> tuple[float, ...]:
        return tuple(1.0 / e for e in self.E_pa)

    @property
    def note(self) -> str:
        """"S2 = S1 + negligible element" where extra elements vanished (or split), else ""."""
        k = sum(bool(v) for v in self.negligible)
        parts = []
        if k:
            parts.append("negligible element" if k == 1 else f"{k} negligible elements")
        if self.model_error_elements:  # (velab.fitting.selection.mark_model_errors)
            k = len(self.model_error_elements)
            parts.append("a model-error element" if k == 1 else f"{k} model-error elements")
        if self.split_elements:
            s = self.split_elements
            parts.append("an element split in two" if s == 1 else f"{s} elements split")
        if not parts:
            return ""
        return (f"{self.name} = {self.equivalent_to} + " if self.equivalent_to else "") + " + ".join(parts)

    def material(self) -> Material:
        return Material(
            wave_speed_m_s=self.wave_speed_m_s,
            elements=tuple(KelvinVoigt(e, h) for e, h in zip(self.E_pa, self.eta_pa_s)),
            name=self.name,
        )

    def elements(self) -> list[dict]:
        m = len(self.E_pa)
        Jr, neg, gain = _nan_tuple(self.J_rel, m), self.negligible or (False,) * m, _nan_tuple(self.element_gain, m)
        se = [_nan_tuple(v, m) for v in (self.E_se_pa, self.eta_se_pa_s, self.tau_se_s, self.J_rel_se)]
        out = []
        for i, (e, h) in enumerate(zip(self.E_pa, self.eta_pa_s)):
            out.append({
                "E": e, "eta": h, "tau": h / e, "J": 1.0 / e, "J_rel": Jr[i], "negligible": bool(neg[i]),
                "gain": gain[i], "E_se": se[0][i], "eta_se": se[1][i], "tau_se": se[2][i],
                "J_se": se[0][i] / (e * e) if math.isfinite(se[0][i]) else math.nan, "J_rel_se": se[3][i],
            })
        return out

    def to_dict(self) -> dict:
        return {
            "name": self.name, "m": self.m, "k": self.k, "reduced": self.reduced, "n": self.n,
            "F": self.F, "rss": self.rss,
            "aic": self.aic, "aicc": self.aicc, "bic": self.bic, "aic_ar1": self.aic_ar1,
            "delta_aic": self.delta_aic, "delta_aic_white": self.delta_aic_white,
            "weight": self.weight, "support": self.support,
            "wave_speed": self.wave_speed_m_s, "wave_speed_se": self.wave_speed_se_m_s,
            "elements": self.elements(),
            "lag1_autocorr": self.lag1_autocorr, "innovation_var": self.innovation_var, "n_eff": self.n_eff,
            "at_bounds": [dict(b) for b in self.at_bounds],
            "equivalent_to": self.equivalent_to or None, "split_elements": self.split_elements,
            "model_error_elements": list(self.model_error_elements), "note": self.note or None,
            "friction": dict(self.friction),
            "noise_ratio": self.noise_ratio, "steady_head_offset": self.steady_head_offset_m,
            "cov_x": [list(row) for row in self.cov_x] if self.cov_x is not None else None,
            "evaluations": self.evaluations, "jacobians": self.jacobians, "starts": self.starts,
        }

    @classmethod
    def from_dict(cls, d: dict) -> "ModelFit":
        """Inverse of :meth:`to_dict`; keys missing in older documents get their defaults."""
        els = d.get("elements") or []

        def col(key):
            return tuple(math.nan if el.get(key) is None else float(el[key]) for el in els)

        def num(key, default=math.nan):
            v = d.get(key, default)
            return default if v is None else float(v)

        m = int(d.get("m", len(els)))
        return cls(
            name=str(d["name"]), m=m, k=int(d.get("k", 2 * m + 1)), reduced=bool(d.get("reduced", False)),
            n=int(d.get("n", 0) or 0), F=num("F"), wave_speed_m_s=num("wave_speed", num("wave_speed_m_s")),
            E_pa=col("E"), eta_pa_s=col("eta"), lag1_autocorr=num("lag1_autocorr"),
            evaluations=int(d.get("evaluations", 0) or 0), jacobians=int(d.get("jacobians", 0) or 0),
            starts=int(d.get("starts", 0) or 0), aic=num("aic"), aicc=num("aicc"), bic=num("bic"),
            delta_aic=num("delta_aic"), weight=num("weight"), support=str(d.get("support") or ""),
            J_rel=col("J_rel") if els and "J_rel" in els[0] else (),
            innovation_var=num("innovation_var"), aic_ar1=num("aic_ar1"), delta_aic_white=num("delta_aic_white"),
            n_eff=num("n_eff"), wave_speed_se_m_s=num("wave_speed_se"),
            E_se_pa=col("E_se") if els and "E_se" in els[0] else (),
            eta_se_pa_s=col("eta_se") if els and "eta_se" in els[0] else (),
            tau_se_s=col("tau_se") if els and "tau_se" in els[0] else (),
            J_rel_se=col("J_rel_se") if els and "J_rel_se" in els[0] else (),
            negligible=tuple(bool(el.get("negligible", False)) for el in els),
            element_gain=col("gain") if els and "gain" in els[0] else (),
            at_bounds=[dict(b) for b in d.get("at_bounds") or []],
            equivalent_to=str(d.get("equivalent_to") or ""), split_elements=int(d.get("split_elements") or 0),
            model_error_elements=tuple(int(k) for k in d.get("model_error_elements") or ()),
            friction=dict(d.get("friction") or {}),
            noise_ratio=_optional(d.get("noise_ratio")), steady_head_offset_m=num("steady_head_offset", 0.0),
            cov_x=_cov_x(d.get("cov_x"), m, bool(d.get("reduced", False))) if d.get("cov_x") is not None else None,
        )


@dataclass
class SweepResult:
    """All models calibrated on one record window, ranked by the selection criterion."""

    n: int
    window_s: float
    sample_rate_hz: float
    method: str
    settings: FitSettings  # (a dict given is read as one: FitSettings.from_dict)
    models: list[ModelFit]
    duration_s: float = 0.0
    evaluations: int = 0  # head-model evaluations over the whole sweep
    notes: list[str] = field(default_factory=list)
    selection: str = "ar1"  # "ar1" (default) or "white" (the paper's AIC)
    # the record's own rate and the anti-alias filter that took it to the fit rate (sample_rate_hz)
    record_rate_hz: float = math.nan
    anti_alias_filter: str = "none"
    # the record's own noise (its pretrigger baseline at the fit rate) and what the fit makes of it
    # (velab.fitting.adequacy): warnings [{"code": "misfit"|"cavitation"|"bound", "message"}]
    baseline_noise_m: float | None = None
    baseline_lag1: float | None = None
    adequacy: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)

    def __post_init__(self):
        if not isinstance(self.settings, FitSettings):
            self.settings = FitSettings.from_dict(self.settings)

    def __setattr__(self, name, value):
        if name == "settings" and not isinstance(value, FitSettings):
            value = FitSettings.from_dict(value)
        super().__setattr__(name, value)

    @property
    def fit_rate_hz(self) -> float:
        return self.sample_rate_hz

    @property
    def best(self) -> ModelFit:
        """The model with the least selection criterion (velab.fitting.selection.best_of)."""
        return best_of(self.models, self.selection)

    @property
    def bounds(self) -> dict:
        return dict(self.settings.get("bounds") or {})

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
        # each model's "creep" and the "creep_averaged" are derived (recomputed from the models when read back)
        return {
            "n": self.n,
            "window": self.window_s,
            "sample_rate_hz": self.sample_rate_hz,
            "record_rate_hz": self.record_rate_hz if math.isfinite(self.record_rate_hz) else self.sample_rate_hz,
            "anti_alias_filter": self.anti_alias_filter,
            "method": self.method,
            "selection": self.selection,
            "settings": self.settings.to_dict(),
            "best": self.best.name,
            "duration_s": self.duration_s,
            "evaluations": self.evaluations,
            "models": [self._model_dict(f) for f in self.models],
            "creep_averaged": self.creep_averaged().to_dict(),
            "notes": list(self.notes),
            "baseline_noise_m": self.baseline_noise_m,
            "baseline_lag1": self.baseline_lag1,
            "adequacy": dict(self.adequacy),
            "warnings": [dict(w) for w in self.warnings],
        }

    def creep(self, fit: ModelFit | None = None, t_s=None):
        """J(t) - J0 of ``fit`` (default: the best model) with its 95 % band, from the lower
        retardation-time bound to the window (velab.fitting.creep)."""
        return creep_of(self, fit if fit is not None else self.best, t_s)

    def creep_averaged(self, t_s=None):
        """The model-averaged J(t) - J0 over the models' Akaike weights, its band unconditional on the model
        (velab.fitting.creep.averaged_creep_of)."""
        return averaged_creep_of(self, t_s)

    def _model_dict(self, f: ModelFit) -> dict:
        d = f.to_dict()
        # the creep curve is derived (recomputed from the elements and cov_x when read back)
        d["creep"] = self.creep(f).to_dict()
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "SweepResult":
        """Inverse of :meth:`to_dict`, tolerant of documents written before a field existed."""
        sel = d.get("selection") or "white"  # documents without it were ranked by the white AIC
        r = cls(
            n=int(d.get("n", 0) or 0), window_s=float(d.get("window", d.get("window_s", math.nan))),
            sample_rate_hz=float(d.get("sample_rate_hz") or math.nan), method=str(d.get("method", "")),
            settings=FitSettings.from_dict(d.get("settings") or {}), models=[ModelFit.from_dict(m) for m in d.get("models") or []],
            duration_s=float(d.get("duration_s") or 0.0), evaluations=int(d.get("evaluations") or 0),
            notes=list(d.get("notes") or []), selection=sel if sel in SELECTIONS else "white",
            record_rate_hz=float(d.get("record_rate_hz") or d.get("sample_rate_hz") or math.nan),
            anti_alias_filter=str(d.get("anti_alias_filter") or "none"),
            baseline_noise_m=_optional(d.get("baseline_noise_m")), baseline_lag1=_optional(d.get("baseline_lag1")),
            adequacy=dict(d.get("adequacy") or {}), warnings=_warnings(d.get("warnings")),
        )
        b = r.bounds
        for f, md in zip(r.models, d.get("models") or []):
            if f.support == "model error" and "model_error_elements" not in md and "tau_min_s" in b:
                # stored before the field existed: the same rule on the fit's own tau box finds them again
                f.model_error_elements = tuple(model_error_elements(f, b["tau_min_s"], b["tau_max_s"]))
        if "warnings" not in d and r.models and r.best.at_bounds:
            # a fit stored before the warnings existed: its parameters on a bound are the one it can have
            r.warnings = [{"code": "bound", "message": bound_message(r.best)}]
        return r

    def warning_codes(self) -> list[str]:
        return [w["code"] for w in self.warnings]


__all__ = ["ModelFit", "SweepResult", "model_name"]
