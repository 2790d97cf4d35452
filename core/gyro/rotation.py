"""Strapdown attitude from sampled rates, vectorised (no per-sample Python loop).

Convention: C_k (3x3) maps vectors in the body frame at sample k to the body frame at the
start (body(0) <- body(k)); C_0 = I and C_k = C_{k-1} exp([omega_k dt]x) with omega in the body
frame [rad/s]. A vector fixed in the world (gravity) seen in the body frame evolves as
g_k = C_k^T g_0.

The running product of N small rotations is an associative scan, done with log2(N) vectorised
quaternion products (Hillis-Steele prefix scan).
"""
from __future__ import annotations

import numpy as np


def quat_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton products p q of quaternion rows (x, y, z, w: scipy's order)."""
    x1, y1, z1, w1 = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    x2, y2, z2, w2 = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                     w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
                     w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2], axis=-1)


def attitude(omega: np.ndarray, dt: float) -> np.ndarray:
    """C_k for k = 1..N (N, 3, 3) from body rates omega (N, 3) [rad/s] sampled every dt [s]."""
    # imported here: scipy.spatial pulls in scipy.sparse/linalg/special, tens of MB the daemon's start avoids
    from scipy.spatial.transform import Rotation  # noqa: PLC0415

    omega = np.asarray(omega, dtype=float).reshape(-1, 3)
    p = Rotation.from_rotvec(omega * dt).as_quat()
    s = 1
    while s < p.shape[0]:  # inclusive prefix scan: p[i] = q_0 q_1 ... q_i
        p[s:] = quat_mul(p[:-s], p[s:])
        s *= 2
    if p.shape[0] == 0:
        return np.zeros((0, 3, 3))
    return Rotation.from_quat(p).as_matrix()


def skew(v: np.ndarray) -> np.ndarray:
    x, y, z = np.asarray(v, dtype=float)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def orthonormal_complement(u: np.ndarray) -> np.ndarray:
    """(3, 2): two unit vectors orthogonal to the unit vector u and to each other."""
    u = np.asarray(u, dtype=float)
    e = np.eye(3)[int(np.argmin(np.abs(u)))]
    a = np.cross(u, e)
    a /= np.linalg.norm(a)
    return np.column_stack([a, np.cross(u, a)])
