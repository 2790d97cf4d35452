"""numpy reference of core/detectors/_movingstd.c (MovingVarianceDetector's signal): the same quantities
by the same float64 operations in the same order, so the two agree bit for bit."""
from __future__ import annotations

import numpy as np


def moving_std(ext: np.ndarray, w: int, sums: np.ndarray, det: np.ndarray) -> None:
    """ext (6, w + n): per row the w values before the block and the block's n values of y (rows 0-2)
    and y² (rows 3-5); sums (6,) the trailing-window sums, advanced in place; det (n,) the max per-axis
    moving std: s += ext[:, w + j] - ext[:, j] (a running sum, left to right),
    var_i = (s_{3+i} - s_i s_i / w) / (w - 1), det = sqrt(max(var_0, var_1, var_2, 0))."""
    if w < 2:
        raise ValueError(f"window must hold at least 2 samples, got {w}")
    ext = np.asarray(ext, dtype=np.float64).reshape(6, -1)
    n = ext.shape[1] - w
    if n < 0:
        raise ValueError(f"ext must be (6, {w} + n)")
    run = np.empty((6, n + 1))
    run[:, 0] = sums
    np.subtract(ext[:, w:], ext[:, :n], out=run[:, 1:])
    np.add.accumulate(run, axis=1, out=run)  # accumulate adds left to right: the kernel's running sums
    s, q = run[:3, 1:], run[3:, 1:]
    var = (q - s * s / float(w)) / float(w - 1)
    det[:] = np.sqrt(np.maximum(np.maximum(np.maximum(var[0], var[1]), var[2]), 0.0))
    sums[:] = run[:, n]
