"""Thermal lag: the zero-g level follows the die temperature, which trails the recorded temperature channel
through a first-order lag, o_i += c_i (T_lag - T_ref), tau dT_lag/dt = T - T_lag.

A board whose temperature sensor sits away from the accelerometer (or in a housing that warms unevenly)
records a temperature the die reaches only after the package and PCB time constant tau. Fitted with a
plain temperature offset, the remainder c (T_lag - T) ~ -c tau dT/dt is smooth in time and is taken for a
drift or a supply effect. The coefficients enter linearly; tau is profiled over a log-spaced grid by
diagnosis (core/diagnosis/terms.py) and stored with the calibration (``lag_tau_s``).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ..base import Context
from ..datasheet import THERMAL_LAG_TAU_S
from ..filters import filter_sections, first_order_section, state_from
from ..lag import first_order_lag
from ..spec import LaggedView, TermSpec, channels_from_axes, column, per_sensitivity
from ..stateful import StatefulTerm


class ThermalLag(StatefulTerm):
    """Offset coef_g_per_c (T_lag - t0_c) per channel [g/°C], T_lag the temperature lagged by tau_s [s];
    state = the lag filter's delay (a T_lag) at the end of the last block (block-split invariant)."""

    name = "thermal_lag"
    stage = "channel"

    def __init__(self, coef_g_per_c: Any = np.zeros(4), t0_c: Any = 25.0, tau_s: Any = THERMAL_LAG_TAU_S,
                 **params: Any):
        super().__init__(coef_g_per_c=coef_g_per_c, t0_c=t0_c, tau_s=tau_s, **params)

    def init_state(self, x: np.ndarray, ctx: Context) -> dict[str, Any]:
        a = float(np.exp(-1.0 / (ctx.fs * float(self.params["tau_s"]))))
        sos = first_order_section([1.0 - a], [1.0, -a])
        return {"sos": sos, "zi": state_from(sos, a * float(np.asarray(ctx.temp, dtype=float).ravel()[0]))}

    def lagged_temp(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        st = self.current_state(x, ctx)
        return filter_sections(st["sos"], np.broadcast_to(np.asarray(ctx.temp, dtype=float), (ctx.n,)), st["zi"])

    def linear_part(self, ctx: Context) -> tuple[np.ndarray, np.ndarray]:
        """Offset at the context's rows, the lag starting at the first row's temperature (no earlier history)."""
        n = ctx.n
        lag = first_order_lag(np.asarray(ctx.t, dtype=float), np.broadcast_to(np.asarray(ctx.temp, dtype=float), (n,)),
                              float(self.params["tau_s"]))
        return np.ones(4), self.params["coef_g_per_c"] * (column(lag) - self.params["t0_c"])

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        return x + self.params["coef_g_per_c"] * (column(self.lagged_temp(x, ctx)) - self.params["t0_c"])


# Switched on with the drift group (a slow offset excursion): the datasheet gives no lag figure, so the
# prior coefficient is 0 (a temperature sensor at the die) and the default simulations draw the same samples;
# the lag control of tests/core/test_diagnose_interacting.py plants one on the window means. (Not the
# temperature group: its oscillator variant is seeded from the group's last term.)
SPEC = TermSpec(
    name="thermal_lag", forward=ThermalLag, group="drift",
    prior=lambda rng: ThermalLag(coef_g_per_c=np.zeros(4)),
    # not in diagnose's default catalogue: on a one-posture recording (the ActiGraph chamber) it is preferred to
    # the temperature offset, but without the held-sensitivity propagation that term's finding carries
    # (core/diagnosis/held.py); diagnose_windows tests it when asked (candidates)
    diagnosed_by=None,
    # acts on the offsets through the lagged temperature; the spread rule is the temperature
    # term's: below 1 °C the lag is a constant the offsets absorb
    view=LaggedView(prefix="oL", covariate="temp", unit="mg_per_C",
                    report_factor=per_sensitivity(1e3), min_span=1.0,
                    span_reason="a lagged temperature term cannot be told from the offsets",
                    convention="offset per °C of the die temperature, the recorded temperature through a "
                               "first-order lag of time constant tau_s (profiled)",
                    profiled=THERMAL_LAG_TAU_S),
    sensor_term=lambda v: {"name": "thermal_lag",
                           "params": {"coef_g_per_c": channels_from_axes(v, 1e-3), "t0_c": 25.0,
                                      "tau_s": float(v.get("tau_s") or THERMAL_LAG_TAU_S)}},
)
