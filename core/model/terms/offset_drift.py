"""Offset drift: the zero-g level wanders with time, o_i += r_o,i (t - t0) (rate) plus a random walk."""
from __future__ import annotations

from typing import Any

import numpy as np

from ..base import Context
from ..datasheet import OFFSET_RATE_G_PER_H, OFFSET_WALK_G_PER_SQRT_H
from ..spec import CalibrationView, TermSpec, channels_from_axes, column, per_sensitivity, signed
from .random_walk import RandomWalkTerm


class OffsetDrift(RandomWalkTerm):
    """Bias rate_g_per_h t + random walk (walk_g_per_sqrt_h) per channel [g]; t in hours."""

    name = "offset_drift"
    stage = "channel"
    rate_key, walk_key = "rate_g_per_h", "walk_g_per_sqrt_h"

    def __init__(self, rate_g_per_h: Any = np.zeros(4), walk_g_per_sqrt_h: Any = np.zeros(4), **params: Any):
        super().__init__(rate_g_per_h=rate_g_per_h, walk_g_per_sqrt_h=walk_g_per_sqrt_h, **params)

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        return x + self.drift(ctx, x)

    def linear_part(self, ctx: Context) -> tuple[np.ndarray, np.ndarray]:
        """Deterministic part only (the random walk has zero mean)."""
        return np.ones(4), self.params["rate_g_per_h"] * (column(ctx.t) / 3600.0)


# 0.5 h: a drift at the datasheet-scale 1 mg/h moves the offsets by 0.5 mg over it, the order of one
# window's noise; over shorter spans a rate cannot be told from the offsets
DRIFT_MIN_SPAN_H = 0.5

SPEC = TermSpec(
    name="offset_drift", forward=OffsetDrift, group="drift",
    prior=lambda rng: OffsetDrift(rate_g_per_h=signed(rng, OFFSET_RATE_G_PER_H, 4),
                                  walk_g_per_sqrt_h=np.full(4, OFFSET_WALK_G_PER_SQRT_H)),
    plant=lambda rng, v, scale: OffsetDrift(rate_g_per_h=v, walk_g_per_sqrt_h=np.zeros(4)),
    plant_scale=3.0e-3,  # g/h
    diagnosed_by="windows",
    view=CalibrationView(prefix="oh", acts_on="offset", covariate="time", unit="mg_per_h",
                         report_factor=per_sensitivity(1e3), min_span=DRIFT_MIN_SPAN_H,
                         span_reason="a drift cannot be told from the offsets"),
    sensor_term=lambda v: {"name": "offset_drift", "params": {"rate_g_per_h": channels_from_axes(v, 1e-3),
                                                             "walk_g_per_sqrt_h": [0.0] * 4}},
)
