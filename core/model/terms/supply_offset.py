"""Supply offset: the zero-g level moves with the supply voltage, o_i += c_V,i (V - V_ref).

The ADXL210's duty-cycle output is not ratiometric to its supply, but its 0 g duty cycle is
(datasheet "0 g duty cycle vs. supply", docs/sensor-model.md): a logger whose battery droops or
whose supply sags under radio load sees offsets move with the supply channel it records.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ..datasheet import SUPPLY_OFFSET_G_PER_V, V_NOMINAL
from ..spec import CalibrationView, TermSpec, channels_from_axes, per_sensitivity, signed
from .linear import CovariateLinearTerm


class SupplyOffset(CovariateLinearTerm):
    """Offset coef_g_per_v (vsupply - v0) per channel [g/V]."""

    name = "supply_offset"
    stage = "channel"
    covariate, coef_key, ref_key, acts_on = "vsupply", "coef_g_per_v", "v0", "offset"

    def __init__(self, coef_g_per_v: Any = np.zeros(4), v0: Any = V_NOMINAL, **params: Any):
        super().__init__(coef_g_per_v=coef_g_per_v, v0=v0, **params)


SPEC = TermSpec(
    name="supply_offset", forward=SupplyOffset, group="supply",
    prior=lambda rng: SupplyOffset(coef_g_per_v=signed(rng, SUPPLY_OFFSET_G_PER_V, 4), v0=V_NOMINAL),
    plant=lambda rng, v, scale: SupplyOffset(coef_g_per_v=v, v0=V_NOMINAL),
    plant_scale=0.05,  # g/V: a fifth of the datasheet figure, found over a 0.25 V droop in an hour
    diagnosed_by="windows",
    # 0.05 V: a logger's regulated supply ripples by a few mV; below 50 mV of spread the term's effect
    # (at the datasheet's 250 mg/V) stays within the quasi-static floor and cannot be told from the offsets
    view=CalibrationView(prefix="oV", acts_on="offset", covariate="vsupply", unit="mg_per_V",
                         report_factor=per_sensitivity(1e3), min_span=0.05,
                         span_reason="a supply term cannot be told from the offsets"),
    sensor_term=lambda v: {"name": "supply_offset",
                           "params": {"coef_g_per_v": channels_from_axes(v, 1e-3), "v0": V_NOMINAL}},
)
