"""Chunked access to a recording's raw triad, whether one (N, 3) array or three columns."""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np


class _Columns:
    """Uniform chunked access to raw as an (N, 3) array/memmap or a sequence of three (N,) columns."""

    def __init__(self, raw: Any):
        if isinstance(raw, (list, tuple)):
            if len(raw) != 3:
                raise ValueError(f"raw must be (N, 3) or three columns, got {len(raw)} columns")
            self.cols: Sequence[np.ndarray] | None = [np.asarray(c) if not isinstance(c, np.ndarray) else c for c in raw]
            n = {c.shape[0] for c in self.cols}
            if len(n) != 1 or any(c.ndim != 1 for c in self.cols):
                raise ValueError("raw columns must be 1-D and of equal length")
            self.n = n.pop()
            self.arr = None
        else:
            arr = raw if isinstance(raw, np.ndarray) else np.asarray(raw)
            if arr.ndim != 2 or arr.shape[1] != 3:
                raise ValueError(f"raw must be (N, 3) (ax, ay, az in raw units), got shape {arr.shape}")
            self.arr, self.cols, self.n = arr, None, arr.shape[0]

    def block(self, i: int, j: int) -> np.ndarray:
        """Rows i..j as float64 (j - i, 3) in Fortran order: each channel converted on its own
        into a contiguous row (3x faster than converting interleaved rows of a structured
        memmap), which is the layout the detectors work in (no further copy)."""
        out = np.empty((3, j - i))
        for k in range(3):
            out[k] = self.arr[i:j, k] if self.arr is not None else self.cols[k][i:j]
        return out.T
