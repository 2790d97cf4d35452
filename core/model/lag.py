"""First-order lag of a covariate sampled at (possibly irregular) times: what a sensor die follows
when its temperature trails the board's temperature channel through a thermal time constant."""
from __future__ import annotations

import numpy as np

from .filters import filter_sections, first_order_section, state_from


def first_order_lag(t: np.ndarray, x: np.ndarray, tau_s: float) -> np.ndarray:
    """y with dy/dt = (x - y) / tau_s, y = x at the earliest time; each x held over the interval ending
    at its time (exact for a piecewise-constant input). Rows in any order; the lag runs in time order."""
    t, x = np.asarray(t, dtype=float).ravel(), np.asarray(x, dtype=float).ravel()
    if t.shape != x.shape:
        raise ValueError(f"lag needs one time per value: {t.size} times for {x.size} values")
    if not (np.isfinite(tau_s) and tau_s > 0):
        raise ValueError(f"lag time constant must be positive and finite, got {tau_s!r} s")
    out = np.empty_like(x)
    if x.size == 0:
        return out
    order = np.argsort(t, kind="stable")
    a = np.exp(-np.diff(t[order], prepend=t[order[0]]) / tau_s)
    y = x[order[0]]
    xs = x[order]
    if xs.size > 1000 and np.ptp(a[1:]) <= 1e-9:  # uniform sampling (samples, not windows): one filter call
        sos = first_order_section([1.0 - a[1]], [1.0, -a[1]])
        out[order] = filter_sections(sos, xs, state_from(sos, a[1] * y))
        return out
    ys = np.empty_like(xs)
    for i in range(xs.size):  # sequential recursion; windows are few, samples go through the compiled filter
        y = a[i] * y + (1.0 - a[i]) * xs[i]
        ys[i] = y
    out[order] = ys
    return out
