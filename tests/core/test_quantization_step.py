"""lsb_of: the grid a static stretch's values sit on, or 0 for continuous values (which must then not be tested
for quantization at all)."""
from __future__ import annotations

import numpy as np
import pytest

from gravcal.core.diagnosis.noise import lsb_of

SEEDS = range(8)


@pytest.mark.parametrize("level", [0.0, 1.0, -5.0, 1000.0, 2048.5])
@pytest.mark.parametrize("n", [200, 20_000])
def test_continuous_values_have_no_grid(level, n):
    for seed in SEEDS:
        x = level + np.random.default_rng(seed).normal(0.0, 0.01 * max(1.0, abs(level)), n)
        assert lsb_of(x) == 0.0, (level, n, seed)


@pytest.mark.parametrize("lsb, offset", [(1.0, 2048.0), (0.0039, 0.0), (0.01, 2000.0), (0.5, 0.25), (1 / 256, -1.0)])
def test_values_on_a_grid_give_its_step(lsb, offset):
    for seed in SEEDS:
        counts = np.round(np.random.default_rng(seed).normal(0.0, 40.0, 5000))
        x = offset + counts * lsb  # each value rounded once, as a reader scaling integer counts does
        got = lsb_of(x)
        assert got == pytest.approx(lsb, rel=1e-9), (lsb, offset, seed)


def test_one_value_off_the_grid_means_no_grid():
    x = np.arange(100, dtype=float) * 0.0039
    x[37] += 0.3 * 0.0039
    assert lsb_of(x) == 0.0
