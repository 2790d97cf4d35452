"""Temperature offset: the zero-g level moves with temperature, o_i += c_T,i (T - T_ref)."""
from __future__ import annotations

from typing import Any

import numpy as np

from ..datasheet import TEMP_OFFSET_G_PER_C
from ..spec import CalibrationView, TermSpec, channels_from_axes, per_sensitivity, signed
from .linear import CovariateLinearTerm


class TemperatureOffset(CovariateLinearTerm):
    """Offset coef_g_per_c (T - t0_c) per channel [g/°C]."""

    name = "temperature_offset"
    stage = "channel"
    covariate, coef_key, ref_key, acts_on = "temp", "coef_g_per_c", "t0_c", "offset"

    def __init__(self, coef_g_per_c: Any = np.zeros(4), t0_c: Any = 25.0, **params: Any):
        super().__init__(coef_g_per_c=coef_g_per_c, t0_c=t0_c, **params)


SPEC = TermSpec(
    name="temperature_offset", forward=TemperatureOffset, group="temperature",
    prior=lambda rng: TemperatureOffset(coef_g_per_c=signed(rng, TEMP_OFFSET_G_PER_C, 4)),
    plant=lambda rng, v, scale: TemperatureOffset(coef_g_per_c=v, t0_c=25.0),
    plant_scale=1.0e-3,  # g/°C (datasheet +-2 mg/°C)
    diagnosed_by="windows",
    # 1 °C: below it c_T (T - T_ref) is a constant within the window noise, indistinguishable from the
    # offsets; whether a wider spread determines the term is the observability rule's call
    view=CalibrationView(prefix="oT", acts_on="offset", covariate="temp", unit="mg_per_C",
                         report_factor=per_sensitivity(1e3), min_span=1.0,
                         span_reason="a temperature term cannot be told from the offsets"),
    sensor_term=lambda v: {"name": "temperature_offset",
                           "params": {"coef_g_per_c": channels_from_axes(v, 1e-3), "t0_c": 25.0}},
)
