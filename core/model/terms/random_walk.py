"""Shared machinery of the drift terms: a deterministic rate times t plus a random walk."""
from __future__ import annotations

from typing import Any

import numpy as np

from ..base import Context
from ..filters import filter_sections, first_order_section, state_from
from ..spec import column
from ..stateful import StatefulTerm

_ACCUMULATE = first_order_section([1.0], [1.0, -1.0])  # y[n] = y[n-1] + x[n]


class RandomWalkTerm(StatefulTerm):
    """rate * t + W(t) per channel, t in hours; state = W at the end of the last block."""

    rate_key: str
    walk_key: str

    def init_state(self, x: np.ndarray, ctx: Context) -> dict[str, Any]:
        return {"walk": state_from(_ACCUMULATE, 0.0, 4)}

    def drift(self, ctx: Context, x: np.ndarray) -> np.ndarray:
        """rate t + W(t) for every sample, (N, 4); advances the walk state."""
        st = self.current_state(x, ctx)
        n = ctx.n
        dt_h = 1.0 / ctx.fs / 3600.0
        steps = st["rng"].standard_normal((n, 4)) * (self.params[self.walk_key] * np.sqrt(dt_h))
        # sequential recursion W[n] = W[n-1] + step: block-split invariant (unlike cumsum + offset)
        walk = filter_sections(_ACCUMULATE, steps, st["walk"])
        return self.params[self.rate_key] * (column(ctx.t) / 3600.0) + walk
