"""Butterworth second-order sections without importing scipy.signal (~76 MB resident and ~0.3 s at start):
orders 1 and 2 in closed form, and the filter's rest state. Used by the streaming detector (core/detectors), the
block detector (core/fastdetect.py), the sensor model's analog filters (core/model/filters.py) and the gyro's
high-pass inverse (core/gyro/conditioning.py), so it imports none of them; tests check it against scipy.signal."""
from __future__ import annotations

import math

import numpy as np


def butter_sos(order: int, corner_hz: float, kind: str, fs: float) -> np.ndarray:
    """signal.butter(order, corner_hz, kind, fs=fs, output="sos") as a C-contiguous (sections, 6)
    array; orders 1 and 2 are the bilinear transform with the corner prewarped, other orders ask SciPy."""
    if order == 1:
        return _butter_first_order(corner_hz, kind, fs)
    if order != 2:
        from scipy import signal  # noqa: PLC0415 (start-up cost: only a non-default filter order needs scipy.signal)

        return np.ascontiguousarray(signal.butter(order, corner_hz, kind, fs=fs, output="sos"))
    k = math.tan(math.pi * corner_hz / fs)
    norm = 1.0 / (1.0 + math.sqrt(2.0) * k + k * k)
    a = [1.0, 2.0 * (k * k - 1.0) * norm, (1.0 - math.sqrt(2.0) * k + k * k) * norm]
    b = [k * k * norm, 2.0 * k * k * norm, k * k * norm] if kind == "lowpass" else [norm, -2.0 * norm, norm]
    return np.array([b + a])


def _butter_first_order(corner_hz: float, kind: str, fs: float) -> np.ndarray:
    """SciPy's steps for N = 1 (iirfilter: pole -1 scaled to the prewarped corner w, bilinear_zpk at fs = 2,
    numpy's complex division x / y = x * (1 / y)) in the same float operations, so the section is SciPy's bit
    for bit: pole (4 - w) / (4 + w), gain 4 / (4 + w) (high-pass, zero at 1) or w / (4 + w) (low-pass, zero at -1)."""
    if not 0.0 < corner_hz < fs / 2.0:  # SciPy's check: Wn = 2 corner / fs in (0, 1)
        raise ValueError(f"filter corner must lie in (0, fs/2 = {fs / 2.0} Hz), got {corner_hz} Hz")
    w = 4.0 * math.tan(math.pi * (2.0 * corner_hz / fs) / 2.0)
    scale = 1.0 / (4.0 + w)
    pole = (4.0 - w) * scale
    if kind == "highpass":
        k = 4.0 * scale
        return np.array([[k, -k, 0.0, 1.0, -pole, 0.0]])
    if kind == "lowpass":
        k = w * scale
        return np.array([[k, k, 0.0, 1.0, -pole, 0.0]])
    raise ValueError(f"filter kind must be 'lowpass' or 'highpass', got {kind!r}")


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
