"""Output range of each channel (the ADXL210's +-10 g)."""
from __future__ import annotations

from typing import Any

import numpy as np

from ..base import Context, Term
from ..datasheet import RANGE_G
from ..spec import TermSpec


class Saturation(Term):
    """Output range: clip each channel to +-limit_g [g]. Samples at the rail get FLAG_SATURATED."""

    name = "saturation"
    stage = "channel"

    def __init__(self, limit_g: Any = np.full(4, RANGE_G), **params: Any):
        super().__init__(limit_g=limit_g, **params)

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        lim = self.params["limit_g"]
        return np.clip(x, -lim, lim)

    def at_rail(self, x: np.ndarray) -> np.ndarray:
        """(N,) True where any channel of the (clipped) channel-stage output is at its limit."""
        return np.any(np.abs(x) >= self.params["limit_g"], axis=1)

    def linear_part(self, ctx: Context) -> tuple[np.ndarray, np.ndarray]:
        return np.ones(4), np.zeros(4)  # identity inside the range


SPEC = TermSpec(name="saturation", forward=Saturation, prior=lambda rng: Saturation(limit_g=np.full(4, RANGE_G)))
