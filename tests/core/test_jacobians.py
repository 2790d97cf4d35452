"""core/estimators/_jacobians.c: the batch fit's corrected accelerations and Jacobians, window by window.

linear_norm_jacobian (offsets, 6, 9, 12): equal to the numpy form it replaced (Parameterization.accel_and_jacobian's
products, norm_and_projection, crlb.h_variance) to the rounding of its three-term products and sums (never to
a BLAS's bits); one row keeps the numpy form.

extended_accel_jacobian: three oracles: its numpy reference (core/estimators/_jacobians_reference.py, the
operations in the kernel's order: equal bit for bit, the kernel is built without fused multiply-add), the
batched-matmul form it replaced (a BLAS adds the three-term products in its own order: equal to a bound derived
from the rounding of those sums), and LAPACK's solve (the adjugate inverse against LU, to the condition number).

Bad buffers are clear errors.
"""
from __future__ import annotations

import numpy as np
import pytest

from gravcal.core.calibration import Calibration
from gravcal.core.estimators import _jacobians
from gravcal.core.estimators._jacobians_reference import dot3, extended_form, inverse_3x3
from gravcal.core.crlb import h_variance
from gravcal.core.estimators.extended import combine_rows, parameterization
from gravcal.core.estimators.parameterization import PARAMETERIZATIONS, norm_and_projection
from gravcal.core.windows import WindowSet

EPS = np.finfo(float).eps


def ordered_form(Kc, oc, p, dK, do, raw):
    """The reference's form: a, J (M, 3, P), K, o and K^-1, every operation in the kernel's order."""
    return extended_form(Kc, oc, p, dK, do, raw)


def matmul_form(Kc, oc, p, dK, do, raw):
    K = Kc[None] + combine_rows(p, dK)
    o = oc[None] + combine_rows(p, do)
    inv = inverse_3x3(K)
    a = np.matmul(inv, (raw - o)[:, :, None])[:, :, 0]
    m, P = dK.shape[:2]
    inner = np.matmul(dK.reshape(m, 3 * P, 3), a[:, :, None]).reshape(m, P, 3) + do
    return a, -np.matmul(inv, inner.transpose(0, 2, 1))


def kernel(Kc, oc, p, dK, do, raw, const=None, entries=None):
    """The kernel on rows given in full (M, P, 3, 3), (M, P, 3): every entry a window value, unless ``entries``
    ((q, e) pairs, e 0-8 in dK_q, 9-11 in do_q) names the ones that vary and ``const`` (P, 12) holds the rest."""
    m, P = dK.shape[:2]
    full = np.concatenate([dK.reshape(m, P, 9), do], axis=2)
    if entries is None:
        entries = np.array([(q, e) for q in range(P) for e in range(12)], dtype=float).reshape(-1, 2)
        const = np.zeros((P, 12))
    idx = entries.astype(int)
    values = np.ascontiguousarray(full[:, idx[:, 0], idx[:, 1]])
    a, J = np.empty((m, 3)), np.empty((m, 3, P))
    _jacobians.extended_accel_jacobian(Kc, oc, p, const, entries, values, raw, a, J, m, P, len(entries))
    return a, J


def sensor_like(rng: np.random.Generator, M: int, P: int):
    """K near 0.04 raw/g with ~1 % cross terms, per-window derivative rows of mixed magnitudes (drifts,
    temperature slopes), means on the ellipsoid: what the extended fits evaluate."""
    Kc = 0.04 * (np.eye(3) + 0.01 * rng.standard_normal((3, 3)))
    oc = 0.5 + 0.01 * rng.standard_normal(3)
    p = rng.standard_normal(P) * 10.0 ** rng.integers(-4, 0, size=P)
    dK = rng.standard_normal((M, P, 3, 3)) * 10.0 ** rng.integers(-6, -1, size=(M, P, 1, 1))
    do = rng.standard_normal((M, P, 3)) * 10.0 ** rng.integers(-6, -1, size=(M, P, 1))
    u = rng.standard_normal((M, 3))
    raw = (u / np.linalg.norm(u, axis=1, keepdims=True)) @ Kc.T + oc
    return Kc, oc, p, dK, do, raw


@pytest.mark.parametrize("M, P", [(0, 3), (1, 1), (1, 9), (7, 6), (1001, 9), (4000, 12), (333, 15)])
def test_kernel_equals_the_ordered_numpy_form_bit_for_bit(M, P):
    rng = np.random.default_rng(10 * M + P)
    args = sensor_like(rng, M, P)
    a, J = kernel(*args)
    wa, wJ, *_ = ordered_form(*args)
    assert np.array_equal(a, wa) and np.array_equal(J, wJ)


@pytest.mark.parametrize("seed", range(3))
def test_kernel_agrees_with_the_batched_matmul_form_to_rounding(seed):
    rng = np.random.default_rng(seed)
    args = sensor_like(rng, 5000, 9)
    Kc, oc, p, dK, do, raw = args
    a, J = kernel(*args)
    ma, mJ = matmul_form(*args)
    _, _, K, o, inv = ordered_form(*args)
    # a three-term sum in any order is within 2 * 2 eps of the exact sum of the rounded products' magnitudes
    # (products rounded alike); J inherits a's difference through |dK| and adds its own two sums
    bound_a = 4 * EPS * dot3(np.abs(inv), np.abs(raw - o))
    assert np.all(np.abs(a - ma) <= bound_a)
    inner_mag = dot3(np.abs(dK), np.broadcast_to((np.abs(a) + bound_a)[:, None, :], do.shape)) + np.abs(do)
    inner_err = dot3(np.abs(dK), np.broadcast_to(bound_a[:, None, :], do.shape)) + 4 * EPS * inner_mag
    bound_J = (dot3(np.abs(inv)[:, None], inner_err) + 4 * EPS * dot3(np.abs(inv)[:, None], inner_mag)).transpose(0, 2, 1)
    assert np.all(np.abs(J - mJ) <= bound_J)
    assert np.any(a != ma) or np.any(J != mJ)  # the orders do differ somewhere: the bound is what is tested


@pytest.mark.parametrize("seed", range(3))
def test_accel_is_lapacks_solution_to_the_condition_number(seed):
    rng = np.random.default_rng(seed)
    Kc, oc, p, dK, do, raw = sensor_like(rng, 2000, 6)
    raw = np.concatenate([raw[:1000], rng.standard_normal((1000, 3))])
    dK[1000:] = rng.standard_normal((1000, 6, 3, 3))  # general matrices too
    a, _ = kernel(Kc, oc, p, dK, do, raw)
    K = Kc[None] + combine_rows(p, dK)
    o = oc[None] + combine_rows(p, do)
    ref = np.linalg.solve(K, (raw - o)[:, :, None])[:, :, 0]
    cond = np.linalg.cond(K)
    err = np.abs(a - ref).max(axis=1) / np.abs(ref).max(axis=1)
    assert np.all(err <= 1e-13 * cond)


def test_a_singular_K_gives_non_finite_values_not_an_error():
    Kc, oc = np.zeros((3, 3)), np.zeros(3)
    dK = np.zeros((2, 1, 3, 3))
    dK[0, 0] = np.eye(3)
    dK[1, 0, 0] = dK[1, 0, 1] = [1.0, 2.0, 3.0]
    a, J = kernel(Kc, oc, np.ones(1), dK, np.zeros((2, 1, 3)), np.ones((2, 3)))
    assert np.array_equal(a[0], np.ones(3)) and np.array_equal(J[0, :, 0], -np.ones(3))
    assert not np.all(np.isfinite(a[1]))


def test_the_bound_parameterization_uses_it():
    rng = np.random.default_rng(4)
    M = 50
    mean = 0.5 + 0.04 * rng.standard_normal((M, 3))
    ws = WindowSet(mean, np.zeros((M, 3, 3)), np.ones(M), np.linspace(0, 7200, M), 25 + rng.standard_normal((M, 1)),
                   np.arange(M), np.arange(M) + 1)
    start = Calibration("6", [0.5, 0.5, 0.5], np.diag([0.04, 0.041, 0.039]))
    for model in ("6+temperature_offset+offset_drift", "9+sensitivity_drift", "6+nonlinearity"):
        par = parameterization(model, start.sensitivity, start.offset)
        bound = par.at_windows(ws)
        q = par.pack(start.sensitivity, start.offset) + 1e-3 * rng.standard_normal(par.n_params)
        a, J = bound.accel_and_jacobian(q, mean)
        wa, wJ, *_ = ordered_form(bound.K_const, bound.o_const, q, bound.dK_rows, bound.do_rows, mean)
        assert np.array_equal(a, wa) and np.array_equal(J, wJ)
        # the kernel's form of the rows (constant rows, the entries term_rows fills per window) is the full one
        rows = np.broadcast_to(bound.const_rows, (M,) + bound.const_rows.shape).copy()
        idx = bound.entries.astype(int)
        rows[:, idx[:, 0], idx[:, 1]] = bound.values
        assert np.array_equal(rows[:, :, :9].reshape(bound.dK_rows.shape), bound.dK_rows)
        assert np.array_equal(rows[:, :, 9:], bound.do_rows)
        assert 0 < len(idx) < rows[0].size  # structure to exploit


@pytest.mark.parametrize("seed", range(4))
def test_leaving_out_the_structural_zeros_changes_no_bit(seed):
    """Rows as the extended models build them (constant base rows, one covariate entry per extra parameter,
    some exactly 0 or -0.0, signed zeros in the constant rows), p with zeros, and the cases that must take the
    full sums: a NaN mean (a not finite), do_q = 0 with a zero dK_q row, a non-finite p."""
    rng = np.random.default_rng(seed)
    M, P = 3000, 12
    const = np.zeros((P, 12))
    for i in range(3):
        const[i, 4 * i] = 1.0  # base sensitivities: dK_i = e_i e_i^T
        const[3 + i, 9 + i] = 1.0  # base offsets: do = e_i
    const[rng.random((P, 12)) < 0.2] *= -1.0  # -0.0 among the constant zeros
    entries = np.array([(6 + i, 4 * i) for i in range(3)] + [(9 + i, 9 + i) for i in range(3)] + [(3, 10), (3, 11)],
                       dtype=float)
    values = rng.standard_normal((M, len(entries))) * (rng.random((M, len(entries))) < 0.9)
    values[rng.random((M, len(entries))) < 0.05] = -0.0
    values[:, -2:] += 2.0  # a parameter moving all three offsets
    dK = np.broadcast_to(const[:, :9].reshape(P, 3, 3), (M, P, 3, 3)).copy()
    do = np.broadcast_to(const[:, 9:], (M, P, 3)).copy()
    idx = entries.astype(int)
    for t, (q, e) in enumerate(idx):
        if e < 9:
            dK[:, q, e // 3, e % 3] = values[:, t]
        else:
            do[:, q, e - 9] = values[:, t]
    Kc = 0.0004 * rng.standard_normal((3, 3)) * (seed % 2)
    oc = np.zeros(3)
    p = np.concatenate([[0.043, 0.0405, 0.038], [0.46, 0.51, 0.5], 1e-4 * rng.standard_normal(6)])
    p[rng.integers(6, P)] = 0.0
    u = rng.standard_normal((M, 3))
    raw = (u / np.linalg.norm(u, axis=1, keepdims=True)) * p[:3] + p[3:6]
    raw[5] = np.nan
    for q in (p, np.where(np.arange(P) == 7, np.inf, p), np.where(np.arange(P) == 9, -np.inf, p)):
        full = kernel(Kc, oc, q, dK, do, raw)
        with np.errstate(invalid="ignore"):
            wa, wJ, *_ = ordered_form(Kc, oc, q, dK, do, raw)
        sparse = kernel(Kc, oc, q, dK, do, raw, const, entries)
        for f, s_, w in zip(full, sparse, (wa, wJ)):
            assert np.array_equal(f, s_, equal_nan=True) and np.array_equal(np.signbit(f), np.signbit(s_))
            assert np.array_equal(f, w, equal_nan=True)


def test_bad_buffers_are_clear_errors():
    Kc, oc, p, *_, raw = sensor_like(np.random.default_rng(5), 4, 2)
    rows, ent, val = np.zeros((2, 12)), np.array([[0.0, 0.0], [1.0, 10.0]]), np.ones((4, 2))
    a, J = np.empty((4, 3)), np.empty((4, 3, 2))
    f = _jacobians.extended_accel_jacobian
    f(Kc, oc, p, rows, ent, val, raw, a, J, 4, 2, 2)
    with pytest.raises(TypeError, match="raw must be float64"):
        f(Kc, oc, p, rows, ent, val, raw.astype(np.float32), a, J, 4, 2, 2)
    with pytest.raises(TypeError, match="values must be a C-contiguous float64"):
        f(Kc, oc, p, rows, ent, np.ones((2, 4)).T, raw, a, J, 4, 2, 2)
    with pytest.raises(TypeError, match="J must be a C-contiguous writable"):
        ro = np.empty((4, 3, 2))
        ro.flags.writeable = False
        f(Kc, oc, p, rows, ent, val, raw, a, ro, 4, 2, 2)
    with pytest.raises(ValueError, match="rows holds 24 values, expected 36"):
        f(Kc, oc, np.ones(3), rows, ent, val, raw, a, J, 4, 3, 2)
    with pytest.raises(ValueError, match="p holds 2 values, expected 3"):
        f(Kc, oc, p, np.zeros((3, 12)), ent, val, raw, a, J, 4, 3, 2)
    with pytest.raises(ValueError, match="entries holds 4 values, expected 6"):
        f(Kc, oc, p, rows, ent, val, raw, a, J, 4, 2, 3)
    for bad in ([[2.0, 0.0]], [[0.0, 12.0]], [[0.5, 0.0]], [[-1.0, 3.0]], [[0.0, np.nan]]):
        with pytest.raises(ValueError, match="need an integer q < P and e < 12"):
            f(Kc, oc, p, rows, np.array(bad), np.ones((4, 1)), raw, a, J, 4, 2, 1)
    with pytest.raises(ValueError, match="P >= 1"):
        f(Kc, oc, p, rows, ent, val, raw, a, J, 4, 0, 2)
    with pytest.raises(ValueError, match="12 P entries"):
        f(Kc, oc, p, rows, ent, val, raw, a, J, 4, 2, 25)
    with pytest.raises(ValueError, match="too large"):
        f(Kc, oc, p, rows, ent, val, raw, a, J, 2**60, 2, 2)
    with pytest.raises(ValueError, match="too large"):
        f(Kc, oc, p, rows, ent, val, raw, a, J, 0, 2**60, 2)
    with pytest.raises(TypeError):
        f(Kc, oc, p, rows, ent, val, [1.0] * 12, a, J, 4, 2, 2)
    with pytest.raises(TypeError):
        f(Kc, oc, p, rows, ent, val, raw, a, J, 4)


# -- linear_norm_jacobian --------------------------------------------------------------------------------
def linear_numpy_form(par, p, raw, cov_mean):
    a, J = par.accel_and_jacobian(p, raw)
    h, B = norm_and_projection(a, J)
    return h, B, a, h_variance(a, np.linalg.inv(par.unpack(p)[0]), cov_mean, h)


U = EPS / 2  # unit roundoff


def linear_bounds(par, p, raw, cov_mean, want):
    """Bounds on |kernel - numpy form| for h, B, a, var. Each of a's components is a three-term product sum:
    in any two orders (fused or not) within 2 · 3u of the sum of the terms' magnitudes; h = |a| moves by at most
    that difference's norm plus its own few roundings; J = -(G a + C) and B = Σ (a_i / h) J_i carry the
    differences of a and h through the magnitudes of their terms and add their own sums; var = g cov g, with
    g = (a / h) K^-1, likewise (a nine-term sum)."""
    h, B, a, var = want
    K, o = par.unpack(p)
    Ki = np.linalg.inv(K)
    G = np.matmul(Ki, par.dK)  # (P, 3, 3)
    C = (par.do @ Ki.T).T  # (3, P)
    e_a = 6 * U * (np.abs(raw - o) @ np.abs(Ki).T)  # (M, 3)
    e_h = np.linalg.norm(e_a, axis=1) + 8 * U * h
    rel = (e_h + np.linalg.norm(e_a, axis=1)) / h  # relative change of a / h
    u = np.abs(a) / h[:, None]
    J_mag = np.einsum("pik,mk->mip", np.abs(G), np.abs(a)) + np.abs(C)[None]  # (M, 3, P)
    J_err = np.einsum("pik,mk->mip", np.abs(G), e_a) + 8 * U * J_mag
    B_mag = np.einsum("mi,mip->mp", u, J_mag)
    e_B = np.einsum("mi,mip->mp", u, J_err) + (2 * rel[:, None] + 12 * U) * B_mag
    g_mag = u @ np.abs(Ki)
    v_mag = np.einsum("mi,mij,mj->m", g_mag, np.abs(cov_mean), g_mag)
    e_v = (4 * rel + 30 * U) * 2 * v_mag
    return e_h, e_B, e_a, e_v


@pytest.mark.parametrize("M", [1, 2, 3, 17, 1754, 12000])
@pytest.mark.parametrize("model", ["offsets", "6", "9", "12"])
def test_linear_kernel_equals_the_numpy_form_to_rounding(model, M):
    rng = np.random.default_rng(M)
    K0 = np.array([[0.043, 0.0004, -0.0007], [0.0002, 0.0405, 0.0011], [-0.0009, 0.0006, 0.038]])
    par = PARAMETERIZATIONS[model](K0, [0.46, 0.51, 0.5])
    p = par.pack(K0, [0.46, 0.51, 0.5]) * (1 + 1e-3 * rng.standard_normal(par.n_params))
    u = rng.standard_normal((M, 3))
    raw = (u / np.linalg.norm(u, axis=1, keepdims=True)) @ K0.T + 0.5 + 1e-3 * rng.standard_normal((M, 3))
    L = rng.standard_normal((M, 3, 3)) * 1e-4
    cov = L @ L.transpose(0, 2, 1)
    got = par.norm_jacobian_variance(p, raw, cov)
    want = linear_numpy_form(par, p, raw, cov)
    for g, w, e in zip(got, want, linear_bounds(par, p, raw, cov, want)):
        assert g.shape == w.shape and np.all(np.abs(g - w) <= e)
    h, B, a = par.norm_and_jacobian(p, raw)
    assert np.array_equal(h, got[0]) and np.array_equal(B, got[1]) and np.array_equal(a, got[2])
    assert par.norm_jacobian_variance(p, raw)[3] is None


def test_linear_kernel_propagates_non_finite_values_as_numpy():
    par = PARAMETERIZATIONS["6"](np.diag([0.04, 0.041, 0.039]), [0.5, 0.5, 0.5])
    p = par.pack(par.K0, par.o0)
    raw = np.full((6, 3), 0.55)
    raw[1, 0], raw[2], raw[3, 2] = np.nan, 0.5, np.inf  # row 2 at the offset: |a| = 0
    cov = np.broadcast_to(np.eye(3) * 1e-8, (6, 3, 3)).copy()
    with np.errstate(invalid="ignore", divide="ignore"):
        got = par.norm_jacobian_variance(p, raw, cov)
        want = linear_numpy_form(par, p, raw, cov)
    for g, w in zip(got, want):  # the same NaN and inf where numpy has them; the finite rows to rounding
        assert np.array_equal(np.isnan(g), np.isnan(w)) and np.array_equal(np.isinf(g), np.isinf(w))
        fin = np.isfinite(w)
        assert np.allclose(g[fin], w[fin], rtol=64 * U, atol=0) and not fin.all()


def test_linear_kernel_bad_buffers_are_clear_errors():
    M, P = 4, 6
    Ki, o, G, C = np.eye(3), np.zeros(3), np.zeros((P, 3, 3)), np.zeros((3, P))
    raw, cov = np.ones((M, 3)), np.zeros((M, 3, 3))
    h, B, a, v = np.empty(M), np.empty((M, P)), np.empty((M, 3)), np.empty(M)
    _jacobians.linear_norm_jacobian(Ki, o, G, C, raw, cov, h, B, a, v, M, P)
    assert np.array_equal(h, np.full(M, np.sqrt(3.0))) and np.array_equal(v, np.zeros(M))
    _jacobians.linear_norm_jacobian(Ki, o, G, C, raw, None, h, B, a, None, M, P)
    with pytest.raises(ValueError, match="M >= 2"):
        _jacobians.linear_norm_jacobian(Ki, o, G, C, raw[:1], None, h[:1], B[:1], a[:1], None, 1, P)
    with pytest.raises(ValueError, match="both be given or both be None"):
        _jacobians.linear_norm_jacobian(Ki, o, G, C, raw, cov, h, B, a, None, M, P)
    with pytest.raises(ValueError, match="G holds 54 values, expected 63"):
        _jacobians.linear_norm_jacobian(Ki, o, G, np.zeros((3, 7)), raw, None, h, B, a, None, M, 7)
    with pytest.raises(ValueError, match="cov holds 36 values, expected 45"):
        _jacobians.linear_norm_jacobian(Ki, o, G, C, np.ones((5, 3)), cov, h, B, a, v, 5, P)
    with pytest.raises(TypeError, match="B must be a C-contiguous writable"):
        ro = np.empty((M, P))
        ro.flags.writeable = False
        _jacobians.linear_norm_jacobian(Ki, o, G, C, raw, None, h, ro, a, None, M, P)
    with pytest.raises(TypeError, match="Kinv must be float64"):
        _jacobians.linear_norm_jacobian(Ki.astype(np.float32), o, G, C, raw, None, h, B, a, None, M, P)
    with pytest.raises(TypeError, match="raw must be a C-contiguous"):
        _jacobians.linear_norm_jacobian(Ki, o, G, C, np.ones((3, M)).T, None, h, B, a, None, M, P)
    with pytest.raises(ValueError, match="too large"):
        _jacobians.linear_norm_jacobian(Ki, o, G, C, raw, None, h, B, a, None, 2**60, P)
