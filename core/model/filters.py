"""The sensor model's recursive filters (analog poles, Gauss-Markov noise, random walks, thermal lags)
without scipy.signal, whose import costs ~1.5 s and ~60 MB in every simulator process.

Each filter is a cascade of second-order sections run by the compiled kernel that reproduces
scipy.signal.sosfilt (core/_blockkernels.c, direct form II transposed). A first-order filter
b = (b0, b1), a = (1, a1) is the section (b0, b1, 0, 1, a1, 0): with b2 = a2 = 0 the kernel's
operations are lfilter's for that filter, so the outputs are lfilter's bit for bit (tests compare
against scipy.signal). State is the kernel's: (signals, sections, 2), carried between blocks.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from ..accelerator import kernels
from ..butterworth import butter_sos, sos_rest_state

sosfilt = kernels("gravcal.core._blockkernels").sosfilt


def first_order_section(b: Sequence[float], a: Sequence[float]) -> np.ndarray:
    """lfilter's (b, a) with len(a) == 2, a[0] == 1 and len(b) <= 2 as one (1, 6) section."""
    b, a = np.atleast_1d(np.asarray(b, dtype=float)), np.atleast_1d(np.asarray(a, dtype=float))
    if a.shape != (2,) or a[0] != 1.0 or not 1 <= b.size <= 2:
        raise ValueError(f"a first-order filter needs a = (1, a1) and one or two b, got b={b.tolist()} a={a.tolist()}")
    return np.array([[b[0], b[1] if b.size == 2 else 0.0, 0.0, 1.0, a[1], 0.0]])


def butterworth_first_order(corner_hz: float, kind: str, fs: float) -> np.ndarray:
    """signal.butter(1, corner_hz, kind, fs=fs, output="sos") bit for bit: one (1, 6) section."""
    return butter_sos(1, corner_hz, kind, fs)


def state_at(sos: np.ndarray, value: np.ndarray | float, signals: int = 1) -> np.ndarray:
    """The (signals, sections, 2) state of a filter that has long seen the constant ``value``
    (one per signal, or one for all): signal.sosfilt_zi(sos) * value."""
    v = np.broadcast_to(np.asarray(value, dtype=float).ravel(), (signals,))
    return np.ascontiguousarray(sos_rest_state(sos)[None] * v[:, None, None])


def state_from(sos: np.ndarray, z0: np.ndarray | float, signals: int = 1) -> np.ndarray:
    """The (signals, 1, 2) state of a first-order section from lfilter's zi (one delay per signal)."""
    if sos.shape[0] != 1:
        raise ValueError(f"lfilter's zi describes one first-order section, the filter has {sos.shape[0]}")
    zi = np.zeros((signals, 1, 2))
    zi[:, 0, 0] = np.broadcast_to(np.asarray(z0, dtype=float).ravel(), (signals,))
    return zi


def filter_sections(sos: np.ndarray, x: np.ndarray, zi: np.ndarray) -> np.ndarray:
    """signal.sosfilt(sos, x, axis=0, zi=...) for x (n,) or (n, signals): the filtered samples, the
    same shape as x; ``zi`` (signals, sections, 2) float64 is advanced in place to the state after them."""
    x = np.asarray(x, dtype=float)
    if x.ndim not in (1, 2):
        raise ValueError(f"filter input must be (samples,) or (samples, signals), got shape {x.shape}")
    cols = x.reshape(x.shape[0], -1)
    if zi.shape != (cols.shape[1], sos.shape[0], 2) or zi.dtype != np.float64 or not zi.flags.c_contiguous:
        raise ValueError(f"filter state must be C-contiguous float64 ({cols.shape[1]}, {sos.shape[0]}, 2), "
                         f"got {zi.dtype} {zi.shape}")
    y = np.array(cols.T, order="C")  # (signals, n), a copy: the kernel filters in place
    sosfilt(np.ascontiguousarray(sos, dtype=float), y, zi)
    return y.T.reshape(x.shape)


def frequency_response(sos: np.ndarray, f_hz: np.ndarray, fs: float) -> np.ndarray:
    """signal.sosfreqz(sos, worN=f_hz, fs=fs)[1]: the cascade's complex gain at f_hz [Hz], each section
    (b0 + b1 z^-1 + b2 z^-2) / (a0 + a1 z^-1 + a2 z^-2) at z = exp(2 pi i f / fs)."""
    zm1 = np.exp(-2j * np.pi * np.asarray(f_hz, dtype=float) / fs)
    h = np.ones_like(zm1)
    for b0, b1, b2, a0, a1, a2 in np.asarray(sos, dtype=float):
        h = h * (b0 + (b1 + b2 * zm1) * zm1) / (a0 + (a1 + a2 * zm1) * zm1)
    return h
