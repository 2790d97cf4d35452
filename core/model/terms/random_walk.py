"""Shared machinery of the drift terms: a deterministic rate times t plus a random walk."""
from __future__ import annotations

from typing import Any

import numpy as np

from ..base import Context
from ..spec import column
from ..stateful import StatefulTerm


class RandomWalkTerm(StatefulTerm):
    """rate * t + W(t) per channel, t in hours; state = W at the end of the last block."""

    rate_key: str
    walk_key: str

    def init_state(self, x: np.ndarray, ctx: Context) -> dict[str, Any]:
        return {"walk": np.zeros(4)}

    def drift(self, ctx: Context, x: np.ndarray) -> np.ndarray:
        """rate t + W(t) for every sample, (N, 4); advances the walk state."""
        from scipy import signal  # noqa: PLC0415 (scipy.signal is heavy; only the simulator needs it)

        st = self.current_state(x, ctx)
        n = ctx.n
        dt_h = 1.0 / ctx.fs / 3600.0
        steps = st["rng"].standard_normal((n, 4)) * (self.params[self.walk_key] * np.sqrt(dt_h))
        # sequential recursion W[n] = W[n-1] + step: block-split invariant (unlike cumsum + offset)
        walk, zf = signal.lfilter([1.0], [1.0, -1.0], steps, axis=0, zi=st["walk"][None, :])
        st["walk"] = zf[0]
        return self.params[self.rate_key] * (column(ctx.t) / 3600.0) + walk
