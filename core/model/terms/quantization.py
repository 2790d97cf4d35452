"""Timer capture of T1 and T2 (catalogue name ``quantization``; diagnosed on static samples)."""
from __future__ import annotations

from typing import Any

import numpy as np

from ..adxl210 import T2_PER_RSET
from ..base import Context
from ..datasheet import RSET_OHM, RSET_TOL, T2_TEMPCO_PPM, TIMER_CLOCK_HZ
from ..spec import TermSpec, column, signed
from ..stateful import StatefulTerm


class Timer(StatefulTerm):
    """Counter capture of T1 and T2.

    T2 = RSET / 125 Mohm per chip (with a temperature coefficient of the oscillator), counted
    by a timer clocked at ``clock_hz``; T1 = d T2 per channel. Output (N, 6): T1 counts of the
    four channels, then T2 counts of chips A and B. With ``async_phase`` = 1 the clock phase
    relative to the PWM edges is random, so a count is floor(T f + U), U ~ U[0, 1): error within
    one count, unbiased; with 0 it is round(T f). Duty cycles are clipped to [0, 1] first.
    """

    name = "timer"
    stage = "counts"

    def __init__(self, rset_ohm: Any = np.full(2, RSET_OHM), clock_hz: Any = TIMER_CLOCK_HZ,
                 tempco_ppm: Any = np.zeros(2), t0_c: Any = 25.0, async_phase: Any = 1.0, **params: Any):
        super().__init__(rset_ohm=rset_ohm, clock_hz=clock_hz, tempco_ppm=tempco_ppm, t0_c=t0_c,
                         async_phase=async_phase, **params)

    @property
    def tick_hz(self) -> float:
        return float(self.params["clock_hz"])

    def t2_seconds(self, temp: Any) -> np.ndarray:
        """(N, 2) PWM period of each chip [s]."""
        p = self.params
        return p["rset_ohm"] * T2_PER_RSET * (1.0 + p["tempco_ppm"] * 1e-6 * (column(temp) - p["t0_c"]))

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        st = self.current_state(x, ctx)
        t2 = self.t2_seconds(ctx.temp) * float(self.params["clock_hz"])  # (N, 2) exact counts
        t1 = np.clip(x, 0.0, 1.0) * t2[:, [0, 0, 1, 1]]
        exact = np.concatenate([t1, t2], axis=1)
        if float(self.params["async_phase"]):
            return np.floor(exact + st["rng"].random(exact.shape))
        return np.round(exact)


SPEC = TermSpec(
    name="timer", catalogue="quantization", forward=Timer, diagnosed_by="samples", sample_test="lsb",
    prior=lambda rng: Timer(
        rset_ohm=np.full(2, RSET_OHM) if rng is None else RSET_OHM * (1 + rng.uniform(-RSET_TOL, RSET_TOL, 2)),
        clock_hz=TIMER_CLOCK_HZ, tempco_ppm=np.zeros(2)),
    # the oscillator drifts with temperature too (it cancels in T1/T2)
    variants={"temperature": lambda term, rng: Timer(**{**term.params, "tempco_ppm": signed(rng, T2_TEMPCO_PPM, 2)})},
)
