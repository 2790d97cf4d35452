"""PlainCorrection: the one-sample form (C) gives the block form's bits, and both are the
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
    one, gyro = np.empty((samples.shape[0], 3)), np.empty(samples.shape[0])
    bias, per_rad_s = float(rng.uniform(1800, 2200)), float(rng.uniform(300, 400))
    seqs = [c.one(samples[i:i + 1], one[i], gyro[i:i + 1], bias, per_rad_s) for i in range(samples.shape[0])]
    assert seqs == samples["seq"].tolist()  # each record's seq, returned for the caller's static decision
    np.testing.assert_array_equal(one, block)
    np.testing.assert_array_equal(gyro, (samples["gyro"].astype(float) - bias) / per_rad_s)
    want = np.linalg.solve(sens, (raw_triad(samples) - offset).T).T * 9.80665
    np.testing.assert_allclose(block, want, rtol=1e-12, atol=1e-12)
    assert np.isnan(block).any(axis=1).sum() > 0


def test_correction_kernel_rejects_wrong_buffers_with_a_clear_error():
    from gravcal.core._correctkernel import correct_row
    from gravcal.core.samples import empty

    c = PlainCorrection(np.full(3, 0.5), 0.04 * np.eye(3))
    row, acc, gyro = empty(1), np.empty(3), np.empty(1)
    with pytest.raises(ValueError, match="56-byte SAMPLE_DTYPE"):
        correct_row(row.tobytes()[:55], c.offset, c.kinv_t, 0.0, 1.0, acc, gyro)
    with pytest.raises(ValueError, match="kinv_t must be 3x3"):
        correct_row(row, c.offset, c.kinv_t[:2], 0.0, 1.0, acc, gyro)
    with pytest.raises(ValueError, match="acc must be 3"):
        correct_row(row, c.offset, c.kinv_t, 0.0, 1.0, np.empty(4), gyro)
    with pytest.raises(TypeError):  # a read-only output
        correct_row(row, c.offset, c.kinv_t, 0.0, 1.0, bytes(24), gyro)
    # a transposed (Fortran-order) K^-T is stored C-contiguous, so the kernel reads it row by row
    assert PlainCorrection(np.zeros(3), np.asfortranarray(np.arange(9.0).reshape(3, 3) + np.eye(3))).kinv_t.flags.c_contiguous
