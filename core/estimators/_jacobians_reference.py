"""numpy reference of core/estimators/_jacobians.c (the batch fit's corrected accelerations and Jacobians,
window by window), elementwise over the windows, every sum written out left to right.

extended_accel_jacobian does the kernel's operations in its order (the kernel is built without fused
multiply-add): the two agree bit for bit. linear_norm_jacobian's kernel adds its three-term products as
OpenBLAS's dgemm does (fused multiply-adds); here they round once per operation, so the two agree to the
rounding of those sums (tests/core/test_jacobians.py derives the bound).
"""
from __future__ import annotations

import numpy as np


def dot3(A: np.ndarray, x: np.ndarray) -> np.ndarray:
    """A (..., 3, 3) @ x (..., 3), each row's three products added left to right."""
    return A[..., 0] * x[..., None, 0] + A[..., 1] * x[..., None, 1] + A[..., 2] * x[..., None, 2]


def inverse_3x3(K: np.ndarray) -> np.ndarray:
    """Adjugate / determinant of a stack (M, 3, 3), elementwise (a singular K gives inf/NaN)."""
    a, b, c = K[:, 0, 0], K[:, 0, 1], K[:, 0, 2]
    d, e, f = K[:, 1, 0], K[:, 1, 1], K[:, 1, 2]
    g, h, i = K[:, 2, 0], K[:, 2, 1], K[:, 2, 2]
    out = np.empty_like(K, dtype=float)
    out[:, 0, 0], out[:, 0, 1], out[:, 0, 2] = e * i - f * h, c * h - b * i, b * f - c * e
    out[:, 1, 0], out[:, 1, 1], out[:, 1, 2] = f * g - d * i, a * i - c * g, c * d - a * f
    out[:, 2, 0], out[:, 2, 1], out[:, 2, 2] = d * h - e * g, b * g - a * h, a * e - b * d
    det = a * out[:, 0, 0] + b * out[:, 1, 0] + c * out[:, 2, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        out /= det[:, None, None]
    return out


def combine_in_order(p: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """sum_q p[q] rows[:, q] from 0.0 in q order (einsum("p,mp...->m...")) for rows (M, P, ...)."""
    out = np.zeros((rows.shape[0],) + rows.shape[2:])
    for q in range(rows.shape[1]):
        out += p[q] * rows[:, q]
    return out


def extended_form(Kc, oc, p, dK, do, raw):
    """a = K(c)^-1 (raw - o(c)) (M, 3), J = da/dp (M, 3, P), K (M, 3, 3), o (M, 3) and K^-1 of every window
    from its rows dK (M, P, 3, 3), do (M, P, 3)."""
    with np.errstate(invalid="ignore", over="ignore"):
        K = Kc[None] + combine_in_order(p, dK)
        o = oc[None] + combine_in_order(p, do)
        inv = inverse_3x3(K)
        a = dot3(inv, raw - o)
        inner = dot3(dK, np.broadcast_to(a[:, None, :], do.shape)) + do  # (M, P, 3)
        J = -dot3(inv[:, None], inner)  # (M, P, 3)
    return a, J.transpose(0, 2, 1), K, o, inv


def extended_accel_jacobian(K_const, o_const, p, rows, entries, values, raw, a, J, M, P, n, threads=-1):
    """a (M, 3) = K(c)^-1 (raw - o(c)), J (M, 3, P) = da/dp, written in place. rows (P, 12): each parameter's
    constant dK_q (9) and do_q (3); entries (n, 2): (q, e) of the entries whose values (M, n) vary by window."""
    rows = np.asarray(rows, dtype=np.float64).reshape(P, 12)
    ent = np.asarray(entries, dtype=np.float64).reshape(n, 2)
    ok = (ent[:, 0] >= 0) & (ent[:, 0] < P) & (ent[:, 1] >= 0) & (ent[:, 1] < 12) & (ent == np.floor(ent)).all(axis=1)
    if not ok.all():
        t = int(np.flatnonzero(~ok)[0])
        raise ValueError(f"entry {t} is ({ent[t, 0]:g}, {ent[t, 1]:g}): need an integer q < P and e < 12")
    full = np.broadcast_to(rows, (M, P, 12)).copy()
    if n:
        full[:, ent[:, 0].astype(int), ent[:, 1].astype(int)] = np.asarray(values, dtype=np.float64).reshape(M, n)
    wa, wJ, *_ = extended_form(np.asarray(K_const, dtype=float).reshape(3, 3), np.asarray(o_const, dtype=float),
                               np.asarray(p, dtype=float), full[:, :, :9].reshape(M, P, 3, 3), full[:, :, 9:],
                               np.asarray(raw, dtype=float).reshape(M, 3))
    a.reshape(M, 3)[:] = wa
    J.reshape(M, 3, P)[:] = wJ


def linear_norm_jacobian(Kinv, o, G, C, raw, cov, h, B, a, var, M, P, threads=-1):
    """A parameterization with constant derivatives: a = K^-1 (raw - o), J = -(G_q a + C[:, q]) with
    G_q = K^-1 dK_q, h = |a|, B = (a / h)^T J, and with cov (M, 3, 3) var = g cov g^T, g = (a / h)^T K^-1."""
    if (cov is None) != (var is None):
        raise ValueError("cov and var must both be given or both be None")
    Ki = np.asarray(Kinv, dtype=float).reshape(3, 3)
    G = np.asarray(G, dtype=float).reshape(P, 3, 3)
    C = np.asarray(C, dtype=float).reshape(3, P)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        d = np.asarray(raw, dtype=float).reshape(M, 3) - np.asarray(o, dtype=float)
        av = dot3(Ki[None], d)  # (M, 3)
        hv = np.sqrt(av[:, 0] * av[:, 0] + av[:, 1] * av[:, 1] + av[:, 2] * av[:, 2])
        u = av / hv[:, None]
        Bv = np.zeros((M, P))
        for i in range(3):
            Ji = -(dot3(G[None, :, i:i + 1, :], np.broadcast_to(av[:, None, :], (M, P, 3)))[..., 0] + C[i][None])
            Bv += u[:, i:i + 1] * Ji
        a.reshape(M, 3)[:], h.reshape(M)[:], B.reshape(M, P)[:] = av, hv, Bv
        if var is not None:
            g = u[:, 0:1] * Ki[0] + u[:, 1:2] * Ki[1] + u[:, 2:3] * Ki[2]  # u @ K^-1
            cv = np.asarray(cov, dtype=float).reshape(M, 3, 3)
            s = np.zeros(M)
            for i in range(3):
                for j in range(3):
                    s += (g[:, i] * cv[:, i, j]) * g[:, j]
            var.reshape(M)[:] = s
