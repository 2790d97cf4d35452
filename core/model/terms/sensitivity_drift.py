"""Sensitivity drift: each gain wanders with time, K_ii += r_s,i (t - t0) (rate) plus a random walk."""
from __future__ import annotations

from typing import Any

import numpy as np

from ..base import Context
from ..datasheet import SENS_RATE_PER_H, SENS_WALK_PER_SQRT_H
from ..spec import CalibrationView, TermSpec, channels_from_axes, column, per_sensitivity, signed
from .offset_drift import DRIFT_MIN_SPAN_H
from .random_walk import RandomWalkTerm


class SensitivityDrift(RandomWalkTerm):
    """Gain 1 + rate_per_h t + random walk (walk_per_sqrt_h) per channel; t in hours."""

    name = "sensitivity_drift"
    stage = "channel"
    rate_key, walk_key = "rate_per_h", "walk_per_sqrt_h"

    def __init__(self, rate_per_h: Any = np.zeros(4), walk_per_sqrt_h: Any = np.zeros(4), **params: Any):
        super().__init__(rate_per_h=rate_per_h, walk_per_sqrt_h=walk_per_sqrt_h, **params)

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        return x * (1.0 + self.drift(ctx, x))

    def linear_part(self, ctx: Context) -> tuple[np.ndarray, np.ndarray]:
        """Deterministic part only (the random walk has zero mean)."""
        return 1.0 + self.params["rate_per_h"] * (column(ctx.t) / 3600.0), np.zeros(4)


SPEC = TermSpec(
    name="sensitivity_drift", forward=SensitivityDrift, group="drift",
    prior=lambda rng: SensitivityDrift(rate_per_h=signed(rng, SENS_RATE_PER_H, 4),
                                       walk_per_sqrt_h=np.full(4, SENS_WALK_PER_SQRT_H)),
    plant=lambda rng, v, scale: SensitivityDrift(rate_per_h=v, walk_per_sqrt_h=np.zeros(4)),
    plant_scale=3.0e-3,  # 1/h = 0.3 %/h
    diagnosed_by="windows",
    view=CalibrationView(prefix="sh", acts_on="sensitivity", covariate="time", unit="pct_per_h",
                         report_factor=per_sensitivity(100.0), min_span=DRIFT_MIN_SPAN_H,
                         span_reason="a drift cannot be told from the sensitivities"),
    sensor_term=lambda v: {"name": "sensitivity_drift", "params": {"rate_per_h": channels_from_axes(v, 1e-2),
                                                                  "walk_per_sqrt_h": [0.0] * 4}},
)
