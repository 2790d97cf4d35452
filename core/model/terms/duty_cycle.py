"""The duty-cycle modulator: acceleration [g] -> T1/T2 of each channel."""
from __future__ import annotations

from typing import Any

import numpy as np

from ..base import Context, Term
from ..datasheet import D0_LIMITS, D0_TYP, SENS_LIMITS, SENS_TYP
from ..spec import TermSpec, spread


class DutyCycle(Term):
    """Duty-cycle modulator: d = d0 + k a per channel; inverse A = (T1/T2 - d0)/k.

    params: ``d0`` (4,) zero-g duty cycle (nominal 0.5), ``k`` (4,) sensitivity [duty/g]
    (nominal 0.04, i.e. 4 %/g).
    """

    name = "duty_cycle"
    stage = "duty"

    def __init__(self, d0: Any = np.full(4, D0_TYP), k: Any = np.full(4, SENS_TYP), **params: Any):
        super().__init__(d0=d0, k=k, **params)

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        return self.params["d0"] + self.params["k"] * x

    def linear_part(self, ctx: Context) -> tuple[np.ndarray, np.ndarray]:
        return self.params["k"] * np.ones(4), self.params["d0"] * np.ones(4)


SPEC = TermSpec(name="duty_cycle", forward=DutyCycle, prior=lambda rng: DutyCycle(
    d0=np.full(4, D0_TYP) if rng is None else spread(rng, D0_TYP, D0_LIMITS, 4),
    k=np.full(4, SENS_TYP) if rng is None else spread(rng, SENS_TYP, SENS_LIMITS, 4)))
