"""PlainCorrection: the one-sample form (Python floats) gives the block form's bits, and both are the
model a = scale * K^-1 (raw - o), NaN where a chip's period T2 is missing."""
from __future__ import annotations

import numpy as np
import pytest

from gravcal.core.correction import PlainCorrection
from gravcal.core.samples import raw_triad
from gravcal.core.simulate import simulate


@pytest.mark.parametrize("seed", range(3))
def test_one_sample_form_equals_the_block_form_and_the_model(seed):
    rng = np.random.default_rng(seed)
    samples = simulate("daily_living", seed=seed, duration=10.0, fs=100.0).samples
    samples["t2"][rng.integers(0, samples.shape[0], 10), rng.integers(0, 2, 10)] = 0
    offset = 0.5 + rng.normal(0, 0.02, 3)
    sens = 0.04 * np.eye(3) + rng.normal(0, 0.002, (3, 3))
    c = PlainCorrection(offset, sens, 9.80665)
    block = c.block(samples)
    one = np.array([c.one(s["t1"].tolist(), s["t2"].tolist()) for s in samples])
    np.testing.assert_array_equal(one, block)
    want = np.linalg.solve(sens, (raw_triad(samples) - offset).T).T * 9.80665
    np.testing.assert_allclose(block, want, rtol=1e-12, atol=1e-12)
    assert np.isnan(block).any(axis=1).sum() > 0
