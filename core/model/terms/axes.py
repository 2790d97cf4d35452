"""The board -> channel stage: projection of the specific force on the four channel axes."""
from __future__ import annotations

from typing import Any

import numpy as np

from ..adxl210 import IDEAL_AXES, N_CHANNELS
from ..base import Context, Term
from ..spec import TermSpec


class Axes(Term):
    """Projection of the specific force (N, 3) [g, board] on the four channel axes (N, 4) [g].

    params: ``u`` (4, 3) sensitive-axis vectors of ax, ay, az, ax2 in the board frame. Any
    mounting error and cross-axis sensitivity is in ``u``; a subclass may build the same
    projection from physical mounting angles (a model holds one projection).
    """

    name = "axes"
    stage = "board"

    def __init__(self, u: Any = IDEAL_AXES, **params: Any):
        super().__init__(u=u, **params)
        if self.params["u"].shape != (N_CHANNELS, 3):
            raise ValueError(f"axes: u must have shape (4, 3), got {self.params['u'].shape}")

    @property
    def matrix(self) -> np.ndarray:
        """(4, 3) channel axes in the board frame."""
        return self.params["u"]

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        u = self.matrix
        # explicit per-row sums (not BLAS): identical results whatever the block length
        return x[:, 0:1] * u[:, 0] + x[:, 1:2] * u[:, 1] + x[:, 2:3] * u[:, 2]


def projection_matrix(model: Any) -> np.ndarray:
    """The (4, 3) channel axes of a model: its one projection term (Axes or a subclass), else ideal."""
    proj = [t for t in model.stage_terms("board") if isinstance(t, Axes)]
    if len(proj) > 1:
        names = " or ".join(repr(t.name) for t in proj)
        raise ValueError(f"sensor model has {len(proj)} axis projections; keep either {names}")
    return proj[0].matrix if proj else IDEAL_AXES


SPEC = TermSpec(name="axes", forward=Axes, prior=lambda rng: Axes())
