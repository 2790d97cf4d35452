"""core/_fitsums.c (or its numpy reference, core/_fitsums_reference.py): the batch fit's per-window sums of
products equal numpy's einsum and norm to the rounding of sums of that many terms (never to numpy's bits: its
einsum may add in another order in another release), and any buffer of the wrong type, layout or length is a
clear error, never a crash (the compiled kernel's checks).

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


U = 2.0 ** -53  # unit roundoff of float64


def sum_bound(n: int, magnitude: np.ndarray) -> np.ndarray:
    """|difference| of two sums of n rounded products in any two orders: each is within (n + 1) u of the
    exact sum of the magnitudes (Higham's bound on recursive and pairwise summation, the product's rounding
    included); both err."""
    return 2 * (n + 1) * U * magnitude


@pytest.mark.parametrize("M, P", SHAPES)
def test_sums_equal_einsum_to_the_rounding_of_their_terms(M, P):
    rng = np.random.default_rng(M * 100 + P)
    p, rows9, rows3 = spread(rng, P), spread(rng, (M, P, 3, 3)), spread(rng, (M, P, 3))
    for rows, spec in ((rows9, "p,mpij->mij"), (rows3, "p,mpi->mi")):
        got, want = combine_rows(p, rows), np.einsum(spec, p, rows)
        assert np.all(np.abs(got - want) <= sum_bound(P, np.einsum(spec, np.abs(p), np.abs(rows))))
    a, J = spread(rng, (M, 3)), spread(rng, (M, 3, P))
    h, B = norm_and_projection(a, J)
    norm = np.linalg.norm(a, axis=1)
    assert np.all(np.abs(h - norm) <= sum_bound(3, norm) + U * norm)  # and the square root's rounding
    u = a / norm[:, None]
    # B's terms use a / h: h's difference enters each term relatively, then the sum of 3 terms
    mag = np.einsum("mi,mip->mp", np.abs(u), np.abs(J))
    rel_h = (np.abs(h - norm) / norm)[:, None]
    assert np.all(np.abs(B - np.einsum("mi,mip->mp", u, J)) <= sum_bound(3, mag) + 2 * (rel_h + U) * mag)
    a, Kinv, C = spread(rng, (M, 3)) + 1.0, spread(rng, (3, 3)), spread(rng, (M, 3, 3))
    g = (a / np.linalg.norm(a, axis=1, keepdims=True)) @ Kinv
    want = np.einsum("mi,mij,mj->m", g, C, g)
    mag = np.einsum("mi,mij,mj->m", np.abs(g), np.abs(C), np.abs(g))
    assert np.all(np.abs(h_variance(a, Kinv, C) - want) <= sum_bound(9, mag) + 2 * U * mag)
    own = norm_and_projection(a, np.zeros((M, 3, 1)))[0]
    assert np.array_equal(h_variance(a, Kinv, C, own), h_variance(a, Kinv, C))  # the same norm given or not


def test_non_finite_values_propagate_as_in_numpy():
    rng = np.random.default_rng(1)
    a, J = rng.standard_normal((50, 3)), rng.standard_normal((50, 3, 6))
    a[3, 1], a[5], J[7, 2, 4], J[9, 0, 0] = np.nan, 0.0, np.inf, -np.inf
    h, B = norm_and_projection(a, J)
    with np.errstate(invalid="ignore", divide="ignore"):
        want_h, want_B = np.linalg.norm(a, axis=1), np.einsum("mi,mip->mp", a / h[:, None], J)
    for got, want in ((h, want_h), (B, want_B)):  # the same NaN and inf, the finite values to rounding
        assert np.array_equal(np.isnan(got), np.isnan(want)) and np.array_equal(np.isinf(got), np.isinf(want))
        assert np.array_equal(got[np.isinf(got)], want[np.isinf(want)])
        fin = np.isfinite(want)
        assert np.allclose(got[fin], want[fin], rtol=16 * U, atol=0) and (~fin).sum() >= 1


def test_views_and_other_dtypes_are_converted_by_the_wrappers():
    # (the fit's arrays are all contiguous; einsum's own order of sums follows the memory layout)
    rng = np.random.default_rng(2)
    J = rng.standard_normal((40, 6, 3)).transpose(0, 2, 1)  # not contiguous
    a = rng.standard_normal((40, 3)).astype(np.float32)
    h, B = norm_and_projection(a, J)
    h64, B64 = norm_and_projection(a.astype(float), np.ascontiguousarray(J))
    assert np.array_equal(h, h64) and np.array_equal(B, B64)  # the wrappers' conversions: the same sums


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
