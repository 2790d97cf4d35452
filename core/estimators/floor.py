"""The quasi-static floor: the variance f² that, added to every window's variance, brings the
reduced chi² of a fit to 1 (sum_k r_k² / (v_k + f²) = dof).

The left side is decreasing in f², so the root is bracketed by [0, hi] and found by Newton steps
kept inside the bracket (bisection when a step leaves it). A dedicated solve instead of
scipy.optimize.brentq: the default calibration path needs nothing else from scipy.optimize,
whose import costs ~0.5 CPU-s, a third of a week's whole calibration.
"""
from __future__ import annotations

import numpy as np

RTOL = 1e-10  # relative tolerance on f²
XTOL = 1e-18  # absolute tolerance on f² [g²]
MAX_STEPS = 200


def quasi_static_floor(r2: np.ndarray, var: np.ndarray, dof: float, tiny: float) -> float:
    """f² [g²] with sum r2 / max(var + f², tiny) = dof; the bracket's top, 10 max(r2), when even
    that leaves the sum above dof, and 0 when the sum is already at or below dof at f² = 0."""
    r2 = np.asarray(r2, dtype=float)
    var = np.asarray(var, dtype=float)

    def excess_and_slope(f2: float) -> tuple[float, float]:
        d = np.maximum(var + f2, tiny)
        w = r2 / d
        return float(np.sum(w) - dof), float(-np.sum(np.where(var + f2 > tiny, w / d, 0.0)))

    lo, hi = 0.0, max(float(np.max(r2)), 1e-12) * 10
    g_hi, _ = excess_and_slope(hi)
    if g_hi >= 0:
        return hi
    x = lo
    g, slope = excess_and_slope(x)
    if g <= 0:
        return 0.0
    for _ in range(MAX_STEPS):
        if g > 0:
            lo = x
        else:
            hi = x
        nxt = x - g / slope if slope < 0 else 0.5 * (lo + hi)
        if not lo < nxt < hi:
            nxt = 0.5 * (lo + hi)
        if abs(nxt - x) <= XTOL + RTOL * abs(nxt) or hi - lo <= XTOL + RTOL * hi:
            return nxt
        x = nxt
        g, slope = excess_and_slope(x)
        if g == 0:
            return x
    return x
