"""extended.inverse_3x3 (the batched closed-form inverse of the extended models' Jacobian) against LAPACK."""
import numpy as np
import pytest

from gravcal.core.estimators.extended import inverse_3x3


@pytest.mark.parametrize("seed", range(5))
def test_inverse_3x3_is_numpys_inverse(seed):
    rng = np.random.default_rng(seed)
    # sensitivity-like matrices (raw units per g ~0.04, cross-axis terms ~1 %) and general ones
    K = np.concatenate([0.04 * (np.eye(3) + 0.01 * rng.standard_normal((500, 3, 3))), rng.standard_normal((500, 3, 3))])
    inv = inverse_3x3(K)
    ref = np.linalg.inv(K)
    cond = np.linalg.cond(K)
    err = np.abs(inv - ref).max(axis=(1, 2)) / np.abs(ref).max(axis=(1, 2))
    assert np.all(err <= 1e-13 * cond)
    np.testing.assert_allclose(np.matmul(inv[:500], K[:500]), np.broadcast_to(np.eye(3), (500, 3, 3)), atol=1e-12)


def test_inverse_3x3_of_a_singular_matrix_is_not_finite():
    K = np.zeros((2, 3, 3))
    K[0] = np.eye(3)
    K[1, 0] = K[1, 1] = [1.0, 2.0, 3.0]
    inv = inverse_3x3(K)
    np.testing.assert_array_equal(inv[0], np.eye(3))
    assert not np.all(np.isfinite(inv[1]))
