"""core/_fitsums.c: the batch fit's per-window sums of products equal numpy's einsum bit for bit (the
oracle below), and any buffer of the wrong type, layout or length is a clear error, never a crash.

Random arrays: several window counts (0, 1, odd sizes, thousands) and parameter counts (1-15, the
orders and extended models), values spanning magnitudes so that any change in the order of the
products or sums changes the rounding somewhere.
"""
from __future__ import annotations

import numpy as np
import pytest

from gravcal.core import _fitsums
from gravcal.core.crlb import h_variance
from gravcal.core.estimators.extended import combine_rows
from gravcal.core.estimators.parameterization import norm_and_projection

SHAPES = [(0, 3), (1, 1), (1, 6), (1, 9), (2, 12), (7, 6), (1001, 9), (4000, 12), (333, 15), (20000, 9)]


def spread(rng: np.random.Generator, shape) -> np.ndarray:
    return rng.standard_normal(shape) * 10.0 ** rng.integers(-6, 6, size=shape)


@pytest.mark.parametrize("M, P", SHAPES)
def test_sums_equal_einsum_bit_for_bit(M, P):
    rng = np.random.default_rng(M * 100 + P)
    p, rows9, rows3 = spread(rng, P), spread(rng, (M, P, 3, 3)), spread(rng, (M, P, 3))
    assert np.array_equal(combine_rows(p, rows9), np.einsum("p,mpij->mij", p, rows9))
    assert np.array_equal(combine_rows(p, rows3), np.einsum("p,mpi->mi", p, rows3))
    a, J = spread(rng, (M, 3)), spread(rng, (M, 3, P))
    h, B = norm_and_projection(a, J)
    assert np.array_equal(h, np.linalg.norm(a, axis=1))
    assert np.array_equal(B, np.einsum("mi,mip->mp", a / np.linalg.norm(a, axis=1)[:, None], J))
    a, Kinv, C = spread(rng, (M, 3)) + 1.0, spread(rng, (3, 3)), spread(rng, (M, 3, 3))
    g = (a / np.linalg.norm(a, axis=1, keepdims=True)) @ Kinv
    want = np.einsum("mi,mij,mj->m", g, C, g)
    assert np.array_equal(h_variance(a, Kinv, C), want)
    assert np.array_equal(h_variance(a, Kinv, C, norm_and_projection(a, np.zeros((M, 3, 1)))[0]), want)


def test_non_finite_values_propagate_as_in_numpy():
    rng = np.random.default_rng(1)
    a, J = rng.standard_normal((50, 3)), rng.standard_normal((50, 3, 6))
    a[3, 1], a[5], J[7, 2, 4], J[9, 0, 0] = np.nan, 0.0, np.inf, -np.inf
    h, B = norm_and_projection(a, J)
    with np.errstate(invalid="ignore", divide="ignore"):
        assert np.array_equal(h, np.linalg.norm(a, axis=1), equal_nan=True)
        assert np.array_equal(B, np.einsum("mi,mip->mp", a / h[:, None], J), equal_nan=True)


def test_views_and_other_dtypes_are_converted_by_the_wrappers():
    # (the fit's arrays are all contiguous; einsum's own order of sums follows the memory layout)
    rng = np.random.default_rng(2)
    J = rng.standard_normal((40, 6, 3)).transpose(0, 2, 1)  # not contiguous
    a = rng.standard_normal((40, 3)).astype(np.float32)
    u = a.astype(float) / np.linalg.norm(a.astype(float), axis=1)[:, None]
    assert np.array_equal(norm_and_projection(a, J)[1], np.einsum("mi,mip->mp", u, np.ascontiguousarray(J)))


def test_bad_buffers_are_clear_errors():
    a, J, h, out = np.ones((4, 3)), np.ones((4, 3, 2)), np.empty(4), np.empty((4, 2))
    _fitsums.norm_project(a, J, h, out, 4, 2)
    assert np.array_equal(h, np.full(4, np.sqrt(3.0))) and np.allclose(out, np.sqrt(3.0), rtol=1e-15)
    with pytest.raises(TypeError, match="float64"):
        _fitsums.norm_project(a.astype(np.float32), J, h, out, 4, 2)
    with pytest.raises(TypeError, match="C-contiguous"):
        _fitsums.norm_project(np.ones((3, 4)).T, J, h, out, 4, 2)
    with pytest.raises(TypeError, match="writable"):
        ro = np.empty((4, 2))
        ro.flags.writeable = False
        _fitsums.norm_project(a, J, h, ro, 4, 2)
    with pytest.raises(ValueError, match="J holds 24 values, expected 36"):
        _fitsums.norm_project(a, J, h, out, 4, 3)
    with pytest.raises(ValueError, match="out holds 8 values, expected 10"):
        _fitsums.combine(np.ones(2), np.ones((5, 2, 2)), out, 5, 2, 2)
    with pytest.raises(ValueError, match=">= 0"):
        _fitsums.quadratic(a, np.ones((4, 3, 3)), np.empty(4), -1)
    with pytest.raises(ValueError, match="too large"):
        _fitsums.combine(np.ones(2), np.ones(4), np.empty(2), 2**61, 2, 2)
    with pytest.raises(TypeError):
        _fitsums.quadratic([1.0, 2.0, 3.0], np.ones((1, 3, 3)), np.empty(1), 1)
    with pytest.raises(TypeError):
        _fitsums.quadratic(b"\0" * 24, np.ones((1, 3, 3)), np.empty(1), 1)
