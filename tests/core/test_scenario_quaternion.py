"""The scenarios' numpy rotation helpers equal scipy's Rotation (so a scenario renders the same
samples without importing scipy.spatial) to the rounding of the operations both take, not to scipy's bits.

Both normalise the quaternion (a sum of four squares, a square root, four divisions: each component within
3u relative) and form each matrix entry or quaternion component from two or three products of unit-sized
components (terms of magnitude <= 2, three or four more roundings): every entry within 16u of the exact value
on each side, so within TOL = 32u of each other."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gravcal.core.scenarios.motion import E_UP
from gravcal.core.scenarios.quaternion import align_quat, inverse_matrices

TOL = 32 * 2.0 ** -53


@pytest.mark.parametrize("seed", range(5))
def test_inverse_matrices_are_scipys_within_rounding(seed):
    q = np.random.default_rng(seed).normal(size=(500, 4)) * np.random.default_rng(seed + 100).uniform(0.1, 10)
    np.testing.assert_allclose(inverse_matrices(q), Rotation.from_quat(q).inv().as_matrix(), rtol=0, atol=TOL)


def _scipy_align(v):
    r, _ = Rotation.align_vectors([E_UP], [v])
    q = r.as_quat()
    return -q if q[3] < 0 else q


@pytest.mark.parametrize("v", [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], np.ones(3) / np.sqrt(3), [0, 0, 1]])
def test_the_alignments_the_scenarios_use_are_scipys_within_rounding(v):
    """The six-position faces (lab.py) and mounting orientation 2 (planner.py), as they call it."""
    v = np.asarray(v, float)
    np.testing.assert_allclose(align_quat(E_UP, v), _scipy_align(v), rtol=0, atol=TOL)


@pytest.mark.parametrize("seed", range(5))
def test_align_quat_is_scipys_for_any_direction(seed):
    rng = np.random.default_rng(seed)
    for v in rng.normal(size=(200, 3)) * rng.uniform(0.01, 100, size=(200, 1)):
        q = align_quat(E_UP, v)
        np.testing.assert_allclose(q, _scipy_align(v), rtol=0, atol=TOL)
        np.testing.assert_allclose(Rotation.from_quat(q).apply(v / np.linalg.norm(v)), E_UP, rtol=0, atol=1e-13)


def test_align_quat_refuses_opposite_directions():
    with pytest.raises(ValueError, match="opposite"):
        align_quat(E_UP, -E_UP)
