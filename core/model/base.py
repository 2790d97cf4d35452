"""The contract of the one sensor model.

A physical effect is a :class:`Term`: a name, a stage, parameters (a dict of arrays) and
a ``forward`` that transforms the signal of its stage. A
:class:`~gravcal.core.model.sensor_model.SensorModel` is an ordered set of terms; running it forward
is the simulator, inverting its calibration-level view (``triad_truth``) is what the estimators do.
Extending the model means adding a Term subclass and its line in the registry (core/model/terms),
never forking the simulator or the estimators.

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

    Subclasses set ``name`` (the catalogue name used in docs, JSON and ``diagnose``) and
    ``stage`` (one of STAGES), and implement ``forward``; their position within the stage is the
    registry's (core/model/terms). ``params`` holds numpy arrays only, so a term serialises to JSON.
    """

    name: ClassVar[str]
    stage: ClassVar[str]

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
