"""Rotation arithmetic the scenarios need, in numpy alone: importing scipy.spatial costs ~37 MB
resident, and the emulated I2C device renders scenarios inside the daemon. Quaternions are
(x, y, z, w), scipy's order; the results equal scipy's Rotation (tests/core check it)."""
from __future__ import annotations

import math

import numpy as np


def inverse_matrices(quats: np.ndarray) -> np.ndarray:
    """(S, 3, 3) matrices of the inverse rotations of ``quats`` (S, 4), normalised first:
    ``Rotation.from_quat(quats).inv().as_matrix()``, the transposes of the rotations' matrices."""
    q = np.asarray(quats, dtype=float).reshape(-1, 4)
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    norm = np.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = -x / norm, -y / norm, -z / norm, w / norm
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    return np.stack([x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw),
                     2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw),
                     2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2], axis=-1).reshape(-1, 3, 3)


def align_quat(target: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The quaternion of the smallest rotation taking the direction ``v`` onto ``target``
    (``Rotation.align_vectors([target], [v])`` for one pair, in scipy's steps: the rotation
    vector cross * theta / sin(theta), then its quaternion). Not for opposite directions, where
    the axis is undefined."""
    t = np.asarray(target, dtype=float) / np.linalg.vector_norm(target)
    u = np.asarray(v, dtype=float) / np.linalg.vector_norm(v)
    cross = np.cross(u, t)
    theta = math.atan2(float(np.linalg.vector_norm(cross)), float(np.sum(t * u)))
    if np.pi - theta < 1e-3:
        raise ValueError("align_quat: opposite directions have no unique smallest rotation")
    if abs(theta) < 1e-3:  # scipy's Taylor series of theta / sin(theta)
        r = cross * (1 + theta * theta / 6 + theta**4 * 7 / 360)
    else:
        r = cross * theta / math.sin(theta)
    angle = float(np.linalg.vector_norm(r))
    if angle <= 1e-3:
        scale = 0.5 - angle**2 / 48 + angle**4 / 3840
    else:
        scale = math.sin(angle / 2) / angle
    return np.concatenate([r * scale, [math.cos(angle / 2)]])
