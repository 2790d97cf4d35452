"""Butterworth second-order sections for the streaming detector without importing scipy.signal
(~76 MB resident and ~0.3 s at start): order 2 in closed form, and the filter's rest state. Used by the
streaming detector and core/fastdetect.py's block detector (tests check both against scipy.signal)."""
from __future__ import annotations

import math

import numpy as np


def butter_sos(order: int, corner_hz: float, kind: str, fs: float) -> np.ndarray:
    """signal.butter(order, corner_hz, kind, fs=fs, output="sos") as a C-contiguous (sections, 6)
    array; order 2 is the bilinear transform with the corner prewarped, other orders ask SciPy."""
    if order != 2:
        from scipy import signal  # noqa: PLC0415 (only for a non-default filter order)

        return np.ascontiguousarray(signal.butter(order, corner_hz, kind, fs=fs, output="sos"))
    k = math.tan(math.pi * corner_hz / fs)
    norm = 1.0 / (1.0 + math.sqrt(2.0) * k + k * k)
    a = [1.0, 2.0 * (k * k - 1.0) * norm, (1.0 - math.sqrt(2.0) * k + k * k) * norm]
    b = [k * k * norm, 2.0 * k * k * norm, k * k * norm] if kind == "lowpass" else [norm, -2.0 * norm, norm]
    return np.array([b + a])


def sos_rest_state(sos: np.ndarray) -> np.ndarray:
    """signal.sosfilt_zi: the (sections, 2) transposed-direct-form-II state at rest for a unit input."""
    zi = np.empty((sos.shape[0], 2))
    gain = 1.0
    for s, (b0, b1, b2, _, a1, a2) in enumerate(sos):
        h = (b0 + b1 + b2) / (1.0 + a1 + a2)  # the section's DC gain
        zi[s, 1] = gain * (b2 - a2 * h)
        zi[s, 0] = gain * (b1 - a1 * h) + zi[s, 1]
        gain *= h
    return zi
