"""Nonlinearity: a quadratic (and cubic) bow of each channel; in calibration, the quadratic part
seen at the window's reference acceleration, o_i += diag(K0)_i c2_i a0_i²."""
from __future__ import annotations

from typing import Any

import numpy as np

from ..base import Context, Term
from ..datasheet import NONLIN_PCT_FS, RANGE_G
from ..spec import CalibrationView, TermSpec, channels_from_axes, signed


class Nonlinearity(Term):
    """x + c2 x^2 + c3 x^3 per channel (c2 [1/g], c3 [1/g^2]); contributes nothing linear."""

    name = "nonlinearity"
    stage = "channel"

    def __init__(self, c2: Any = np.zeros(4), c3: Any = np.zeros(4), **params: Any):
        super().__init__(c2=c2, c3=c3, **params)

    @classmethod
    def from_percent_fs(cls, pct: Any, full_scale_g: float = RANGE_G) -> "Nonlinearity":
        """Pure quadratic bow with max deviation ``pct`` % of full scale at +-full scale."""
        c2 = np.asarray(pct, float) / 100.0 * full_scale_g / full_scale_g**2
        return cls(c2=np.broadcast_to(c2, (4,)), c3=np.zeros(4))

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        p = self.params
        return x + p["c2"] * x**2 + p["c3"] * x**3

    def linear_part(self, ctx: Context) -> tuple[np.ndarray, np.ndarray]:
        return np.ones(4), np.zeros(4)


def _prior(rng: np.random.Generator | None) -> Nonlinearity:
    c2 = NONLIN_PCT_FS / 100.0 / RANGE_G  # max deviation 0.2 % FS at full scale
    return Nonlinearity(c2=signed(rng, c2, 4), c3=signed(rng, c2 / RANGE_G / 2, 4))


SPEC = TermSpec(
    name="nonlinearity", forward=Nonlinearity, prior=_prior, group="nonlinearity",
    plant=lambda rng, v, scale: Nonlinearity(c2=v, c3=np.zeros(4)),
    plant_scale=4.0e-3,  # c2 [1/g]; the datasheet's 0.2 % FS at 10 g (2e-4) is far below an hour's floor
    diagnosed_by="windows",
    view=CalibrationView(prefix="q2", acts_on="offset", covariate="accel", unit="c2_per_g",
                         report_factor=lambda s: np.ones(3)),
    sensor_term=lambda v: {"name": "nonlinearity", "params": {"c2": channels_from_axes(v, 1.0), "c3": [0.0] * 4}},
)
