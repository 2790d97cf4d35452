"""numpy reference of core/_fitsums.c (the batch fit's per-window sums of products): each sum starts
from 0.0 and adds its products one after another in index order, elementwise over the windows, as the
kernel does; so the two agree bit for bit."""
from __future__ import annotations

import numpy as np


def combine(coef: np.ndarray, rows: np.ndarray, out: np.ndarray, m: int, p: int, k: int) -> None:
    """out[m, j] = sum_q coef[q] rows[m, q, j] (einsum("p,mpk->mk"))."""
    r = np.asarray(rows, dtype=np.float64).reshape(m, p, k)
    o = out.reshape(m, k)
    o[:] = 0.0
    for q in range(p):
        o += coef[q] * r[:, q, :]


def norm_project(a: np.ndarray, J: np.ndarray, h: np.ndarray, B: np.ndarray, m: int, p: int) -> None:
    """h[m] = |a_m| (sqrt((a0² + a1²) + a2²)) and B[m, q] = sum_i (a[m, i] / h[m]) J[m, i, q]."""
    a = np.asarray(a, dtype=np.float64).reshape(m, 3)
    Jm = np.asarray(J, dtype=np.float64).reshape(m, 3, p)
    h[:] = np.sqrt((a[:, 0] * a[:, 0] + a[:, 1] * a[:, 1]) + a[:, 2] * a[:, 2])
    b = B.reshape(m, p)
    b[:] = 0.0
    with np.errstate(invalid="ignore", divide="ignore"):  # |a| = 0 or NaN: NaN rows, as the kernel's
        for c in range(3):
            b += (a[:, c] / h)[:, None] * Jm[:, c, :]


def quadratic(g: np.ndarray, C: np.ndarray, out: np.ndarray, m: int) -> None:
    """out[m] = sum_ij (g_i C_ij) g_j, terms added in (i, j) order (einsum("mi,mij,mj->m"))."""
    g = np.asarray(g, dtype=np.float64).reshape(m, 3)
    C = np.asarray(C, dtype=np.float64).reshape(m, 3, 3)
    s = np.zeros(m)
    for i in range(3):
        for j in range(3):
            s += (g[:, i] * C[:, i, j]) * g[:, j]
    out[:] = s
