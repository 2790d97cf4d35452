"""Bounds on how far two implementations of one cascade of second-order sections (direct form II
transposed) may differ when each rounds its operations in its own order: derived from the operation count,
the coefficients and the filter's gains, never from either implementation's bits."""
from __future__ import annotations

from functools import lru_cache

import numpy as np

U = 2.0 ** -53  # unit roundoff of float64


def _l1_response(sos: np.ndarray, impulse: float, z0: np.ndarray, n: int = 1 << 16) -> float:
    """Σ_k |y_k| of the cascade from state z0 (sections, 2) with input ``impulse`` at k = 0 and 0 after."""
    z = np.array(z0, dtype=float)
    total, v0 = 0.0, impulse
    for k in range(n):  # float64; its own rounding is far below the gains it measures
        v = v0 if k == 0 else 0.0
        for s, (b0, b1, b2, _, a1, a2) in enumerate(sos):
            out = b0 * v + z[s, 0]
            z[s, 0] = b1 * v - a1 * out + z[s, 1]
            z[s, 1] = b2 * v - a2 * out
            v = out
        total += abs(v)
        if k > 64 and abs(v) < 1e-18 * total and not np.any(np.abs(z) > 1e-18 * total):
            break
    return total


def cascade_gains(sos: np.ndarray, n: int = 1 << 16) -> tuple[float, float, float]:
    sos = np.ascontiguousarray(sos, dtype=float)
    return _cascade_gains(sos.tobytes(), sos.shape[0], n)


@lru_cache(maxsize=256)
def _cascade_gains(coefficients: bytes, sections: int, n: int) -> tuple[float, float, float]:
    """(G_in, G_state, G_inner): the l1 gain from the input to the output, the largest from a unit error in
    any section's state (where a rounding error lands) to the output, the largest from the input to any
    section's output; over the first n samples (a signal of n samples sees no more)."""
    sos = np.frombuffer(coefficients, dtype=float).reshape(sections, 6)
    ns = sos.shape[0]
    g_in = _l1_response(sos, 1.0, np.zeros((ns, 2)), n)
    g_inner = max(_l1_response(sos[:s + 1], 1.0, np.zeros((s + 1, 2)), n) for s in range(ns))
    g_state = 0.0
    for s in range(ns):
        for j in range(2):
            z = np.zeros((ns - s, 2))
            z[0, j] = 1.0
            g_state = max(g_state, _l1_response(sos[s:], 0.0, z, n))
    return g_in, g_state, g_inner


def sosfilt_difference_bound(sos: np.ndarray, x_max: float, z_max: float, n: int = 1 << 16,
                             signal_max: float | None = None) -> float:
    """Largest |y_A - y_B| of two DF2T implementations of ``sos`` that round differently, on an input with
    |x| <= x_max from states with |z| <= z_max. Every signal in the cascade stays below
    S = (x_max + z_max) (1 + G_inner) (1 + G_state); per sample and section each implementation rounds at
    most 7 operations, each by at most u times the terms it combines, bounded by (Σ|coefficients| + 2) S;
    every error lands in a state and reaches the output through G_state (at most 1 + G_state, the output's
    own rounding included); both implementations err: twice. ``signal_max``: a known bound on every signal in
    the cascade (e.g. from the outputs of a one-section filter) instead of S; n: the signal's length."""
    sos = np.asarray(sos, float)
    g_in, g_state, g_inner = cascade_gains(sos, n)
    if signal_max is None:
        signal_max = (x_max + z_max) * (1.0 + max(g_in, g_inner)) * (1.0 + g_state)
    coef = float(np.max(np.abs(sos[:, [0, 1, 2, 4, 5]]).sum(axis=1))) + 2.0
    return 2.0 * 7 * sos.shape[0] * U * coef * signal_max * (1.0 + g_state)


def first_order_design_bound(corner: float, fs: float) -> tuple[float, float, float]:
    """Relative bounds (high-pass gain, low-pass gain, pole) on |butter_sos(1) - signal.butter(1)| per
    coefficient of the section (k, ±k, 0, 1, -pole, 0). Both take
    w = 4 tan(x), x = pi (2 corner / fs) / 2 (three roundings, amplified by tan's condition number
    2x / sin 2x, and tan's own error of at most 2 u in any libm), then 1 / (4 + w), (4 - w) / (4 + w) and
    4 / (4 + w) or w / (4 + w) in a few rounded operations each; relative errors add, and both sides err."""
    x = np.pi * (2.0 * corner / fs) / 2.0
    rel_w = 2 * U + 3 * U * (2 * x / np.sin(2 * x))
    w = 4.0 * np.tan(x)
    rel_scale = 2 * U + rel_w * w / (4.0 + w)
    rel_k_hp, rel_k_lp = rel_scale, rel_w + rel_scale + U
    rel_pole = 2 * U + rel_w * w / abs(4.0 - w) + rel_scale
    return 2 * rel_k_hp, 2 * rel_k_lp, 2 * rel_pole
