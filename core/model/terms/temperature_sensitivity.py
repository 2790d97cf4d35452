"""Temperature sensitivity: each channel's gain moves with temperature, K_ii += k_T,i (T - T_ref)."""
from __future__ import annotations

from typing import Any

import numpy as np

from ..datasheet import TEMP_SENS_PER_C
from ..spec import CalibrationView, TermSpec, channels_from_axes, per_sensitivity, signed
from .linear import CovariateLinearTerm


class TemperatureSensitivity(CovariateLinearTerm):
    """Gain (1 + coef_per_c (T - t0_c)) per channel [1/°C]."""

    name = "temperature_sensitivity"
    stage = "channel"
    covariate, coef_key, ref_key, acts_on = "temp", "coef_per_c", "t0_c", "gain"

    def __init__(self, coef_per_c: Any = np.zeros(4), t0_c: Any = 25.0, **params: Any):
        super().__init__(coef_per_c=coef_per_c, t0_c=t0_c, **params)


SPEC = TermSpec(
    name="temperature_sensitivity", forward=TemperatureSensitivity, group="temperature",
    prior=lambda rng: TemperatureSensitivity(coef_per_c=signed(rng, TEMP_SENS_PER_C, 4)),
    plant=lambda rng, v, scale: TemperatureSensitivity(coef_per_c=v, t0_c=25.0),
    plant_scale=5.0e-4,  # 1/°C = 0.05 %/°C (datasheet typ 0.01 %/°C: below an hour's floor)
    diagnosed_by="windows",
    view=CalibrationView(prefix="sT", acts_on="sensitivity", covariate="temp", unit="pct_per_C",
                         report_factor=per_sensitivity(100.0), min_span=1.0,
                         span_reason="a temperature term cannot be told from the sensitivities"),
    sensor_term=lambda v: {"name": "temperature_sensitivity",
                           "params": {"coef_per_c": channels_from_axes(v, 1e-2), "t0_c": 25.0}},
)
