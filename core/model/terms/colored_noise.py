"""Colored noise (bias instability / flicker); diagnosed on static samples (Allan deviation)."""
from __future__ import annotations

from typing import Any

import numpy as np

from ..base import Context
from ..datasheet import BIAS_INSTABILITY_G, BIAS_TAU_S
from ..filters import filter_sections, first_order_section, state_from
from ..spec import TermSpec
from ..stateful import StatefulTerm


class ColoredNoise(StatefulTerm):
    """Sum of first-order Gauss-Markov processes per channel.

    params: ``sigma_g`` (4,) total stationary std [g], ``tau_s`` (k,) correlation times [s]
    (log-spaced times of equal variance approximate a 1/f spectrum between them).
    State: the filter states of the k processes (they start in their stationary distribution).
    """

    name = "colored_noise"
    stage = "channel"

    def __init__(self, sigma_g: Any = np.zeros(4), tau_s: Any = (1.0, 10.0, 100.0), **params: Any):
        super().__init__(sigma_g=sigma_g, tau_s=np.atleast_1d(np.asarray(tau_s, float)), **params)

    def _phi(self, fs: float) -> np.ndarray:
        return np.exp(-1.0 / (fs * self.params["tau_s"]))

    def init_state(self, x: np.ndarray, ctx: Context) -> dict[str, Any]:
        k = self.params["tau_s"].size
        s = self.params["sigma_g"] / np.sqrt(k)
        p0 = self.state["rng"].standard_normal((k, 4)) * s  # stationary start
        phi = self._phi(ctx.fs)
        sections = [first_order_section([1.0], [1.0, -phi[j]]) for j in range(k)]
        return {"sections": sections, "zi": [state_from(sections[j], phi[j] * p0[j], 4) for j in range(k)]}

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        st = self.current_state(x, ctx)
        k = self.params["tau_s"].size
        s = self.params["sigma_g"] / np.sqrt(k)
        phi = self._phi(ctx.fs)
        w = st["rng"].standard_normal((x.shape[0], k, 4))  # sample-major: block-split invariant
        out = np.array(x, dtype=float, copy=True)
        for j in range(k):  # k is 2-4 processes, not samples
            out += filter_sections(st["sections"][j], w[:, j] * (s * np.sqrt(1.0 - phi[j] ** 2)), st["zi"][j])
        return out

    def linear_part(self, ctx: Context) -> tuple[np.ndarray, np.ndarray]:
        return np.ones(4), np.zeros(4)


SPEC = TermSpec(name="colored_noise", forward=ColoredNoise, group="drift", diagnosed_by="samples", sample_test="allan",
                prior=lambda rng: ColoredNoise(sigma_g=np.full(4, BIAS_INSTABILITY_G), tau_s=BIAS_TAU_S))
