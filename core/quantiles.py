"""np.median's and np.percentile's values without numpy.ma.

numpy's median checks its result for NaN through ``np.ma.isMaskedArray`` and its percentile partitions
at ``np.unique`` positions, which asks ``np.ma.is_masked``: the first such call imports numpy.ma
(~15-25 ms, several % of a day's whole `gravcal calibrate`, which needs neither masked arrays nor
anything else of it). These functions do numpy's own arithmetic (numpy/lib/_function_base_impl.py
``_median``, ``_quantile`` with method "linear", ``_lerp``), so their results are numpy's bit for bit
(tests/core/test_quantiles.py).
"""
from __future__ import annotations

from typing import Any

import numpy as np


def median(a: Any, axis: int | None = None) -> Any:
    """np.median(a, axis) for axis None or an int (no out/overwrite_input/keepdims)."""
    a = np.asanyarray(a)
    if axis is None:
        a, axis = a.ravel(), 0
    axis = axis % max(a.ndim, 1)
    n = a.shape[axis]
    if n == 0:
        return np.median(a, axis=axis)  # numpy's own warning and NaN
    half = n // 2
    kth = [half - 1, half] if n % 2 == 0 else [half]
    nans = np.issubdtype(a.dtype, np.inexact)
    if nans:
        kth.append(n - 1)
    part = np.partition(a, kth, axis=axis)
    middle = np.take(part, np.arange(half - 1, half + 1) if n % 2 == 0 else np.arange(half, half + 1), axis=axis)
    out = np.mean(middle, axis=axis)
    if nans:
        last = np.isnan(np.take(part, n - 1, axis=axis))
        if np.ndim(out) == 0:
            return np.take(part, n - 1, axis=axis) if last else out
        out[last] = np.nan
    return out


def percentile(a: Any, q: float) -> Any:
    """np.percentile(a, q) of a float64 array (flattened) and one q in [0, 100], method "linear"; any
    other input goes to np.percentile itself."""
    arr = np.asarray(a)
    if arr.dtype != np.float64 or arr.size == 0 or not (np.ndim(q) == 0 and 0 <= q <= 100):
        return np.percentile(a, q)
    arr = arr.flatten()
    n = arr.shape[0]
    virtual = (n - 1) * np.true_divide(q, 100)  # the sorted position of q
    lo = hi = -1 if virtual >= n - 1 else (0 if virtual < 0 else None)
    if lo is None:
        lo = int(np.floor(virtual))
        hi = lo + 1
    arr.partition(sorted({0, n - 1, lo % n, hi % n}))  # NaN sorts to the end
    below, above = arr[lo], arr[hi]
    gamma = float(virtual - lo)
    diff = above - below
    out = below + diff * gamma if gamma < 0.5 else above - diff * (1 - gamma)
    return arr[-1] if np.isnan(arr[-1]) else out
