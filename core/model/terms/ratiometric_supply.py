"""Ratiometric supply: each channel's gain moves with the supply voltage (simulation only: on a
regulated logger supply the gain change is far below what quasi-static windows resolve)."""
from __future__ import annotations

from typing import Any

import numpy as np

from ..datasheet import SUPPLY_GAIN_PER_V, V_NOMINAL
from ..spec import TermSpec, signed
from .linear import CovariateLinearTerm


class RatiometricSupply(CovariateLinearTerm):
    """Supply dependence of the gain: x (1 + gain_per_v dV), dV = vsupply - v0 [V]."""

    name = "ratiometric_supply"
    stage = "channel"
    covariate, coef_key, ref_key, acts_on = "vsupply", "gain_per_v", "v0", "gain"

    def __init__(self, gain_per_v: Any = np.zeros(4), v0: Any = V_NOMINAL, **params: Any):
        super().__init__(gain_per_v=gain_per_v, v0=v0, **params)


SPEC = TermSpec(
    name="ratiometric_supply", forward=RatiometricSupply, group="supply",
    prior=lambda rng: RatiometricSupply(gain_per_v=signed(rng, SUPPLY_GAIN_PER_V, 4), v0=V_NOMINAL),
)
