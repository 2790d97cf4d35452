"""White noise of each channel (the ADXL210's noise density over the sampled band)."""
from __future__ import annotations

from typing import Any

import numpy as np

from ..base import Context
from ..datasheet import NOISE_DENSITY_UG
from ..spec import TermSpec
from ..stateful import StatefulTerm


class Noise(StatefulTerm):
    """White noise of density density_ug [µg/√Hz] over bandwidth_hz (0 = fs/2, the sampled band).

    Added before the analog low-pass, which then shapes it like the Cx/Cy filter does. The
    only state is the term's own random stream.
    """

    name = "noise"
    stage = "channel"

    def __init__(self, density_ug: Any = np.full(4, NOISE_DENSITY_UG), bandwidth_hz: Any = 0.0, **params: Any):
        super().__init__(density_ug=density_ug, bandwidth_hz=bandwidth_hz, **params)

    def sigma_g(self, fs: float) -> np.ndarray:
        """Per-sample standard deviation [g] at sample rate fs."""
        bw = float(self.params["bandwidth_hz"]) or fs / 2.0
        return self.params["density_ug"] * 1e-6 * np.sqrt(bw)

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        st = self.current_state(x, ctx)
        return x + st["rng"].standard_normal(x.shape) * self.sigma_g(ctx.fs)

    def linear_part(self, ctx: Context) -> tuple[np.ndarray, np.ndarray]:
        return np.ones(4), np.zeros(4)


SPEC = TermSpec(name="noise", forward=Noise, prior=lambda rng: Noise(density_ug=np.full(4, NOISE_DENSITY_UG)))
