"""What a registered term declares: its forward model, prior, planting and calibration view.

A :class:`TermSpec` is the one record of a physical effect that everything outside the term's
own module reads: the simulator builds the forward :class:`~gravcal.core.model.base.Term` from
``prior``; the estimators extend the Lötters parameterization (eq. 13) with the rows the
:class:`CalibrationView` declares; the order rules ask the view whether the windows can test
the term; diagnosis plants it with ``plant`` and names it in the view's report units.

Calibration-level view (window means, triad x, y, z). At a window with covariate value z_i on
axis i a term with parameters p_i (one per axis) changes the reference K, o by

    acts_on "offset"       o_i  += p_i z_i
    acts_on "sensitivity"  K_ii += p_i z_i
    acts_on "cross"        K_ij = K_ji += p_ij   (constant: the symmetric cross-axis part)
    a LaggedView           o_i += p_i z_i, z the covariate through a first-order lag (time constant
    (acts_on "lagged_offset") ``profiled``, chosen by diagnosis; needs the windows' history, so never online)

and z is the deviation of the covariate from its reference: temperature [°C] from T_ref, supply
[V] from V_ref, time [h] from t0, or the squared reference acceleration (diag K0 a0²) for a
quadratic nonlinearity.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, ClassVar

import numpy as np

from .base import Term

AXES = ("x", "y", "z")
CROSS_PAIRS = ((0, 1), (0, 2), (1, 2))


@dataclass(frozen=True)
class Covariate:
    """An exogenous input a term's effect depends on. ``aux_column``: its column in the windows'
    ``aux`` (None: not an aux channel); ``ref_key``: the calibration metadata key of its reference."""

    name: str
    label: str
    unit: str
    aux_column: int | None
    ref_key: str | None
    default_ref: float


COVARIATES: dict[str, Covariate] = {
    "temp": Covariate("temp", "temperature", "°C", 0, "t_ref_c", 25.0),
    "vsupply": Covariate("vsupply", "supply voltage", "V", 1, "v_ref", 3.3),
    "time": Covariate("time", "time", "h", None, "t0_s", 0.0),
    "accel": Covariate("accel", "reference acceleration", "g²", None, None, 0.0),
}
AUX_COLUMNS: tuple[str, ...] = tuple(c.name for c in sorted((c for c in COVARIATES.values() if c.aux_column is not None),
                                                             key=lambda c: c.aux_column))
"""Names of the windows' aux columns, in column order (temperature [°C], supply voltage [V])."""


@dataclass(frozen=True, kw_only=True)
class CalibrationView:
    """A term's calibration-level view (module docstring).

    prefix: parameter names are ``<prefix>_x`` ... (``m_xy`` ... for "cross"), unique in the registry
    (the parameters' position is the registry's, core/model/terms); unit / report_factor: magnitudes in
    report units, per axis, from raw-unit parameters and the diagonal sensitivities s [raw/g]; min_span: the
    smallest spread (5-95 %) of the covariate, in its unit, at which the windows can test the term (None: always);
    convention: the definition of the reported value, copied into every finding's magnitude;
    profiled: the default of a nonlinear time constant [s] (a :class:`LaggedView`'s) that the fit profiles
    instead of estimating linearly (None: the term is linear in its parameters).
    """

    ACTS_ON: ClassVar[tuple[str, ...]] = ("offset", "sensitivity", "cross")
    lagged: ClassVar[bool] = False
    """The rows need the windows' history (a lag), not the window alone."""

    prefix: str
    acts_on: str  # one of ACTS_ON
    covariate: str | None
    unit: str
    report_factor: Callable[[np.ndarray], np.ndarray]
    min_span: float | None = None
    span_reason: str = ""
    convention: str = ""  # how the reported value is defined, when the unit alone does not say it
    profiled: float | None = None

    def __post_init__(self) -> None:
        if self.acts_on not in self.ACTS_ON:
            raise ValueError(f"calibration view {self.prefix!r}: acts_on must be one of {self.ACTS_ON}, "
                             f"got {self.acts_on!r}")
        if self.covariate is not None and self.covariate not in COVARIATES:
            raise ValueError(f"calibration view {self.prefix!r}: unknown covariate {self.covariate!r}; "
                             f"known: {', '.join(COVARIATES)}")

    @property
    def on_offset(self) -> bool:
        return self.acts_on == "offset" or self.lagged

    @property
    def per_window(self) -> bool:
        """A window's rows need no other window: what the recursive (online) estimator requires."""
        return not self.lagged

    @property
    def deviation_key(self) -> str | None:
        """Key of the per-window deviation this term's rows use: its covariate, or the lagged covariate."""
        if self.covariate is None:
            return None
        return self.covariate + ("_lagged" if self.lagged else "")

    @property
    def keys(self) -> list[str]:
        if self.acts_on == "cross":
            return [f"{AXES[i]}{AXES[j]}" for i, j in CROSS_PAIRS]
        return list(AXES)

    def param_names(self) -> list[str]:
        return [f"{self.prefix}_{k}" for k in self.keys]

    @property
    def through_sensitivity(self) -> bool:
        """The term acts through the sensitivities: it cannot be told from the offsets in one posture."""
        return self.acts_on in ("sensitivity", "cross") or self.covariate == "accel"

    def effect_std_g(self, std: np.ndarray, s: np.ndarray, span: float) -> np.ndarray:
        """Std [g] of the term's effect per axis over the covered covariate ``span``."""
        if self.acts_on == "cross":
            return std / np.sqrt([s[i] * s[j] for i, j in CROSS_PAIRS])
        if self.covariate == "accel":
            return std  # relative, per g² at 1 g
        return std * span / s

    def testability(self, values: np.ndarray | None) -> tuple[bool, str]:
        """Can windows with these covariate ``values`` (None: the recording has no such channel) test
        the term? Returns (testable, the reason when not)."""
        if self.covariate is None or self.covariate == "accel" or self.min_span is None:
            return True, ""
        cov = COVARIATES[self.covariate]
        what = cov.label
        if values is None:
            return False, f"the windows carry no {what} (no {cov.name} channel)"
        values = np.asarray(values, dtype=float)
        if values.size == 0:
            return False, "no windows"
        bad = int(np.sum(~np.isfinite(values)))
        if bad:
            return False, f"{bad} of {values.size} windows carry no {what} (the {cov.name} channel reads no value)"
        lo, hi = np.percentile(values, [5, 95])
        if hi - lo < self.min_span:
            return False, (f"no {what} spread: the windows span {hi - lo:.2g} {cov.unit} (5-95 %) < {self.min_span:g} "
                           f"{cov.unit}, so {self.span_reason}")
        return True, ""


@dataclass(frozen=True, kw_only=True)
class LaggedView(CalibrationView):
    """A lagged offset (module docstring): acts on the offsets through its covariate lagged by a first-order
    filter whose time constant (``profiled``, required) the fit profiles; a window's rows need the windows'
    history, so the term is offline only."""

    ACTS_ON: ClassVar[tuple[str, ...]] = ("lagged_offset",)
    lagged: ClassVar[bool] = True

    acts_on: str = field(default="lagged_offset", init=False)
    profiled: float

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.covariate in (None, "accel", "time"):
            raise ValueError(f"calibration view {self.prefix!r}: a lag needs a recorded covariate, "
                             f"got {self.covariate!r}")


def per_sensitivity(scale: float) -> Callable[[np.ndarray], np.ndarray]:
    """Report factor of offset and sensitivity terms: a raw-unit parameter divided by the axis'
    sensitivity s [raw/g] is g (offset) or a relative change (sensitivity) per covariate unit; times
    ``scale`` (1e3: mg, 100: %)."""
    return lambda s: scale / s


@dataclass(frozen=True)
class TermSpec:
    """A registered term (module docstring).

    name: the term's name in models and JSON; catalogue: its name in diagnose's catalogue;
    forward: the Term class; prior: (rng, None for nominal) -> Term from the datasheet spreads;
    group: the ``gravcal simulate`` flag that switches it on (None: in every default model);
    variants: group -> (term, rng) -> the term changed by that group (the temperature group gives the
    timer oscillator a temperature coefficient); plant: (rng, scale) -> Term for a planted test
    effect, given the per-channel values drawn by ``planted_values`` (rng, values, scale), plant_scale its
    test magnitude; diagnosed_by: "windows" (residuals of window
    means), "samples" (noise tests on static samples) or None; sample_test: which static-sample test
    finds it ("allan": the Allan deviation beyond white noise, "lsb": a quantisation step; the tests
    are core/diagnosis/noise.py's); view: None for a simulation-only term.
    """

    name: str
    forward: type[Term]
    prior: Callable[[np.random.Generator | None], Term]
    group: str | None = None
    catalogue: str | None = None
    variants: dict[str, Callable[[Term, np.random.Generator | None], Term]] = field(default_factory=dict)
    plant: Callable[[np.random.Generator, np.ndarray, float], Term] | None = None
    plant_scale: float | None = None
    diagnosed_by: str | None = None
    sample_test: str | None = None
    view: CalibrationView | None = None
    sensor_term: Callable[[dict[str, float]], dict[str, Any]] | None = None

    @property
    def catalogue_name(self) -> str:
        return self.catalogue or self.name


def signed(rng: np.random.Generator | None, typ: float, n: int) -> np.ndarray:
    """Zero-mean draw with sigma typ; nominal (rng None): +typ, -typ alternating per channel."""
    if rng is None:
        return typ * np.array([1.0, -1.0] * ((n + 1) // 2))[:n]
    return rng.normal(0.0, typ, n)


def spread(rng: np.random.Generator, typ: float, limits: tuple[float, float], n: int) -> np.ndarray:
    """Normal draw with mean typ and (max - min)/6 as sigma, clipped to the limits."""
    lo, hi = limits
    return np.clip(rng.normal(typ, (hi - lo) / 6.0, n), lo, hi)


def planted_values(rng: np.random.Generator, scale: float, n: int = 4) -> np.ndarray:
    """Per-channel planted magnitudes: random sign x U(1, 2) x scale."""
    return scale * rng.uniform(1.0, 2.0, n) * np.where(rng.random(n) < 0.5, -1.0, 1.0)


def channels_from_axes(values: dict[str, float], factor: float) -> list[float]:
    """Per-axis report values -> the four channels (ax, ay, az, ax2 = x, y, z, x), times ``factor``."""
    return [factor * float(values.get(a) or 0.0) for a in ("x", "y", "z", "x")]  # undetermined (None): no effect


def column(v: Any) -> np.ndarray:
    """Per-sample scalar (N,) -> (N, 1) for broadcasting against the (N, 4) channels."""
    return np.asarray(v, dtype=float).reshape(-1, 1)
