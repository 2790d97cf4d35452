"""core/estimators/_jacobians.c on two threads: from 4096 windows on (threads=-1) each kernel shares its
windows' chunks with a helper thread. Every output equals the one-thread loop's bit for bit (the windows
are independent), for even and odd window counts, around the threshold, with non-finite windows in the
chunks of either thread and window-dependent rows (each lane works on its own copy of them). The one-thread loop itself is checked
against the numpy forms in tests/core/test_jacobians.py."""
from __future__ import annotations

import numpy as np
import pytest

from gravcal.core.estimators import _jacobians

COUNTS = [2, 3, 4095, 4096, 9999]


def _linear_inputs(rng, M, P):
    Ki = np.linalg.inv(np.diag([0.04, 0.041, 0.039]) + 4e-4 * rng.standard_normal((3, 3)))
    o = 0.5 + 0.01 * rng.standard_normal(3)
    G, C = 1e-2 * rng.standard_normal((P, 3, 3)), 1e-2 * rng.standard_normal((3, P))
    raw = 0.5 + 0.04 * rng.standard_normal((M, 3))
    L = 1e-4 * rng.standard_normal((M, 3, 3))
    raw[M // 3, 1], raw[-1, 0], raw[M // 2] = np.nan, np.inf, o  # non-finite in both halves; |a| = 0 in one
    return Ki, o, G, C, raw, L @ L.transpose(0, 2, 1)


def _linear(inputs, M, P, threads, with_var=True):
    Ki, o, G, C, raw, cov = inputs
    h, B, a, v = np.full(M, 7.0), np.full((M, P), 7.0), np.full((M, 3), 7.0), np.full(M, 7.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        _jacobians.linear_norm_jacobian(Ki, o, G, C, raw, cov if with_var else None, h, B, a, v if with_var else None,
                                        M, P, threads)
    return h, B, a, v


@pytest.mark.parametrize("M", COUNTS)
@pytest.mark.parametrize("P", [3, 6, 12])
def test_linear_halves_equal_one_loop(M, P):
    inputs = _linear_inputs(np.random.default_rng(M * 100 + P), M, P)
    for with_var in (True, False):
        one = _linear(inputs, M, P, 1, with_var)
        for threads in (2, -1):
            for g, w in zip(_linear(inputs, M, P, threads, with_var), one):
                assert np.array_equal(g, w, equal_nan=True)
        assert not np.any(one[0] == 7.0)  # every window written


def _extended_inputs(rng, M, P):
    Kc = np.diag([0.04, 0.041, 0.039]) + 4e-4 * rng.standard_normal((3, 3))
    oc = 0.5 + 0.01 * rng.standard_normal(3)
    p = 1e-3 * rng.standard_normal(P)
    const = np.zeros((P, 12))
    const[:, :9] = 1e-2 * rng.standard_normal((P, 9)) * (rng.random((P, 9)) < 0.5)
    const[:, 9:] = 1e-2 * rng.standard_normal((P, 3))
    entries = np.array([(q, e) for q in range(P) for e in (0, 4, 10) if (q + e) % 2 == 0], dtype=float)
    values = 1e-2 * rng.standard_normal((M, len(entries)))  # rows that change from window to window
    raw = 0.5 + 0.04 * rng.standard_normal((M, 3))
    raw[M // 4, 2], raw[-2, 1] = np.nan, -np.inf
    return Kc, oc, p, const, entries, values, raw


def _extended(inputs, M, P, threads):
    Kc, oc, p, const, entries, values, raw = inputs
    a, J = np.full((M, 3), 7.0), np.full((M, 3, P), 7.0)
    with np.errstate(invalid="ignore"):
        _jacobians.extended_accel_jacobian(Kc, oc, p, const, entries, values, raw, a, J, M, P, len(entries), threads)
    return a, J


@pytest.mark.parametrize("M", COUNTS)
@pytest.mark.parametrize("P", [1, 4, 9])
def test_extended_halves_equal_one_loop(M, P):
    inputs = _extended_inputs(np.random.default_rng(M * 10 + P), M, P)
    one = _extended(inputs, M, P, 1)
    for threads in (2, -1):
        for g, w in zip(_extended(inputs, M, P, threads), one):
            assert np.array_equal(g, w, equal_nan=True)
    assert not np.any(one[1] == 7.0)
    assert np.isfinite(one[0]).all(axis=1).sum() >= M - 2  # only the two non-finite windows are not finite


def test_extended_lanes_keep_their_own_rows():
    """Long enough that the helper and the caller work at the same time: each must fill in its own copy of
    the window-dependent rows (a shared copy is overwritten between a window's filling and its use)."""
    M, P = 200_000, 9
    inputs = _extended_inputs(np.random.default_rng(7), M, P)
    one = _extended(inputs, M, P, 1)
    for _ in range(3):
        for g, w in zip(_extended(inputs, M, P, 2), one):
            assert np.array_equal(g, w, equal_nan=True)


def test_a_forked_child_shares_with_its_own_helper():
    """fork copies only the calling thread: the child's calls must neither wait for the parent's helper
    nor find its locks held (a study's workers may be forked after a fit)."""
    import os

    M, P = 20_000, 6
    inputs = _linear_inputs(np.random.default_rng(8), M, P)
    one = _linear(inputs, M, P, 1)
    _linear(inputs, M, P, 2)  # the parent's helper exists now
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child reports through its exit status
        ok = all(all(np.array_equal(g, w, equal_nan=True) for g, w in zip(_linear(inputs, M, P, 2), one))
                 for _ in range(3))
        os._exit(0 if ok else 1)
    _, status = os.waitpid(pid, 0)
    assert os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0


def test_threads_must_be_one_two_or_automatic():
    M, P = 4, 3
    Ki, o, G, C, raw, cov = _linear_inputs(np.random.default_rng(0), M, P)
    h, B, a, v = np.empty(M), np.empty((M, P)), np.empty((M, 3)), np.empty(M)
    with pytest.raises(ValueError, match="threads must be 1, 2 or -1"):
        _jacobians.linear_norm_jacobian(Ki, o, G, C, raw, cov, h, B, a, v, M, P, 3)
    Kc, oc, p, const, entries, values, raw = _extended_inputs(np.random.default_rng(1), M, P)
    with pytest.raises(ValueError, match="threads must be 1, 2 or -1"):
        _jacobians.extended_accel_jacobian(Kc, oc, p, const, entries, values, raw, np.empty((M, 3)),
                                           np.empty((M, 3, P)), M, P, len(entries), 0)
