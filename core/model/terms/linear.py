"""Shared forward model of the terms linear in one covariate: an offset c (z - z0) or a gain 1 + c (z - z0)."""
from __future__ import annotations

from typing import ClassVar

import numpy as np

from ..base import Context, Term
from ..spec import column


class CovariateLinearTerm(Term):
    """Per channel c (z - z0), z the Context's ``covariate`` (``temp`` [°C], ``vsupply`` [V]); ``coef_key``
    and ``ref_key`` name the parameters. ``acts_on`` "offset": x + c dz; "gain": x (1 + c dz)."""

    covariate: ClassVar[str]
    coef_key: ClassVar[str]
    ref_key: ClassVar[str]
    acts_on: ClassVar[str]

    def deviation(self, ctx: Context) -> np.ndarray:
        return self.params[self.coef_key] * (column(getattr(ctx, self.covariate)) - self.params[self.ref_key])

    def linear_part(self, ctx: Context) -> tuple[np.ndarray, np.ndarray]:
        d = self.deviation(ctx)
        return (np.ones(4), d) if self.acts_on == "offset" else (1.0 + d, np.zeros(4))

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        d = self.deviation(ctx)
        return x + d if self.acts_on == "offset" else x * (1.0 + d)
