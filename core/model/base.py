"""The contract of the one sensor model.

A physical effect is a :class:`Term`: a name, a stage, parameters (a dict of arrays) and
a ``forward`` that transforms the signal of its stage. A :class:`SensorModel` is an
ordered set of terms; running it forward is the simulator, inverting its calibration-level
view (``triad_truth``) is what the estimators do. Extending the model means adding a
Term subclass (and registering it), never forking the simulator or the estimators.

Signal flow through the stages (in this order)::

    board     (N, 3)  specific force in the board frame [g]
      -> projected on the four channel axes by the "axes" term (the stage change)
    channel   (N, 4)  acceleration along each ADXL210 channel axis [g]
      -> noise, nonlinearity, temperature terms, drift, saturation, analog low-pass
    duty      (N, 4)  duty cycle T1/T2 of each channel (a duty-stage term maps g -> duty)
    counts    timer quantisation of T1 and T2 (a counts-stage term with a clock, ``tick_hz``) -> the sample layout
    gyro      (N,)    the ENC-03J path: angular rate [rad/s] -> ADC counts

Each term reads exogenous inputs (time, temperature, supply voltage) from a
:class:`Context`. Randomness comes only from ``ctx.rng``, so a seed reproduces a session.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

STAGES: tuple[str, ...] = ("board", "channel", "duty", "counts", "gyro")


@dataclass
class Context:
    """Exogenous inputs of one simulated block, all arrays of length N."""

    t: np.ndarray  # time [s]
    temp: np.ndarray  # board temperature [°C]
    vsupply: np.ndarray  # supply voltage [V]
    fs: float  # sample rate [Hz]
    rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng())  # numpy.random loads on use
    omega: np.ndarray | None = None  # (N, 3) angular rate in the board frame [rad/s], for the gyro stage

    @property
    def n(self) -> int:
        return int(np.asarray(self.t).shape[0])


class Term(ABC):
    """One named physical effect with its own parameters.

    Subclasses set ``name`` (the catalogue name used in docs, JSON and ``diagnose``),
    ``stage`` (one of STAGES) and ``order`` (position within the stage), and implement
    ``forward``. ``params`` holds numpy arrays only, so a term serialises to JSON.
    """

    name: ClassVar[str]
    stage: ClassVar[str]
    order: ClassVar[int] = 50

    def __init__(self, **params: Any):
        self.params: dict[str, np.ndarray] = {k: np.asarray(v, dtype=float) for k, v in params.items()}

    @abstractmethod
    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        """Transform the signal of this term's stage."""

    def at_rail(self, x: np.ndarray) -> np.ndarray | None:
        """(N,) True where this channel-stage term clipped ``x`` (the sample says nothing beyond its
        rail: flagged saturated); None for a term without rails."""
        return None

    @property
    def tick_hz(self) -> float | None:
        """The clock [Hz] a counts-stage term measures time with (the sample's ``tick`` field counts
        it); None for other terms."""
        return None

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "params": {k: v.tolist() for k, v in self.params.items()}}

    def __repr__(self) -> str:
        ps = ", ".join(f"{k}={np.array2string(v, precision=4)}" for k, v in self.params.items())
        return f"{type(self).__name__}({ps})"


TERM_REGISTRY: dict[str, type[Term]] = {}


def register(cls: type[Term]) -> type[Term]:
    """Class decorator: make a term constructible by its catalogue name."""
    if cls.stage not in STAGES:
        raise ValueError(f"term {cls.__name__}: unknown stage {cls.stage!r}")
    TERM_REGISTRY[cls.name] = cls
    return cls


def term_from_dict(d: dict[str, Any]) -> Term:
    try:
        cls = TERM_REGISTRY[d["name"]]
    except KeyError as exc:
        raise ValueError(f"unknown sensor-model term {d.get('name')!r}; known: {sorted(TERM_REGISTRY)}") from exc
    return cls(**d.get("params", {}))


class SensorModel:
    """An ordered collection of terms, at most one per name."""

    def __init__(self, terms: list[Term]):
        names = [t.name for t in terms]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ValueError(f"sensor model has duplicate terms: {sorted(dup)}")
        self.terms: list[Term] = sorted(terms, key=lambda t: (STAGES.index(t.stage), t.order))

    def __contains__(self, name: str) -> bool:
        return any(t.name == name for t in self.terms)

    def __getitem__(self, name: str) -> Term:
        for t in self.terms:
            if t.name == name:
                return t
        raise KeyError(f"sensor model has no term {name!r}; it has {[t.name for t in self.terms]}")

    def with_term(self, term: Term) -> "SensorModel":
        """A new model with ``term`` added, replacing any term of the same name."""
        return SensorModel([t for t in self.terms if t.name != term.name] + [term])

    def without(self, name: str) -> "SensorModel":
        return SensorModel([t for t in self.terms if t.name != name])

    def stage_terms(self, stage: str) -> list[Term]:
        return [t for t in self.terms if t.stage == stage]

    def run_stage(self, stage: str, x: np.ndarray, ctx: Context) -> np.ndarray:
        for term in self.stage_terms(stage):
            x = term.forward(x, ctx)
        return x

    def to_dict(self) -> dict[str, Any]:
        return {"terms": [t.to_dict() for t in self.terms]}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "SensorModel":
        return cls([term_from_dict(t) for t in d["terms"]])

    def __repr__(self) -> str:
        return "SensorModel(\n  " + ",\n  ".join(repr(t) for t in self.terms) + "\n)"
