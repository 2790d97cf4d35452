"""Terms with explicit state (filters, random walks, private random streams).

A :class:`StatefulTerm` keeps its state in ``self.state`` (``None`` until the first block),
filterpy-style: the state is visible, resettable, and carried from one ``forward`` call to
the next, so simulating a session in blocks gives the same samples as simulating it in one go.

Why a private random stream: several stochastic terms draw from randomness in every block.
If they all drew from the shared ``ctx.rng``, the interleaving of their draws would depend
on the block split. Instead each term seeds its own generator from ``ctx.rng`` on its first
block (in the fixed order of the model's terms) and draws only from that afterwards.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from .base import Context, Term


class StatefulTerm(Term):
    """A term whose output depends on earlier blocks. Subclasses implement ``init_state``."""

    def __init__(self, **params: Any):
        super().__init__(**params)
        self.state: dict[str, Any] | None = None

    def reset(self) -> None:
        """Forget all state: the next block starts a new session."""
        self.state = None

    def init_state(self, x: np.ndarray, ctx: Context) -> dict[str, Any]:
        """State at the start of a session, given the first block (override; default empty)."""
        return {}

    def current_state(self, x: np.ndarray, ctx: Context) -> dict[str, Any]:
        """The carried state, created on the first block (with this term's own random stream)."""
        if self.state is None:
            seed = int(ctx.rng.integers(0, 2**63 - 1))
            st = {"rng": np.random.default_rng(seed)}
            self.state = st  # init_state may use st["rng"]
            st.update(self.init_state(x, ctx))
        return self.state


def reset_model(model: Any) -> None:
    """Reset every stateful term of a SensorModel in place."""
    for term in model.terms:
        if isinstance(term, StatefulTerm):
            term.reset()
