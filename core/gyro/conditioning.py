"""Undoing the ENC-03J board's analog high-pass, so rates integrate to the right angles.

The conditioning stage (core/model/enc03j.py, ``gyro_conditioning``) high-passes the sensor
voltage at ``hp_hz`` (0.3 Hz by default, tau = 1/(2 pi hp_hz) = 0.53 s) before the ADC. Its DC
gain is zero, so the integral of the conditioned signal over a rotation and the following rest
is zero whatever the angle turned: a pose change cannot be measured from it directly. The
first-order section is known, so it can be inverted exactly (a first-order pole at z = 1, i.e.
an integrator, with explicit state):

    HP:       y[n] = b0 (x[n] - x[n-1]) - a1 y[n-1]
    inverse:  x[n] = x[n-1] + (y[n] + a1 y[n-1]) / b0

Started at rest (HP settled, y at the reference), the inverse gives the rate (in counts above
the reference) exactly. Started in the middle of a high-pass tail, it gives the rate plus a
constant C0, found from the tail's shape (``tail_offset``); a bias error delta in the reference
adds a ramp delta (1 + t / tau), which keeps the bias estimate important (0.06 counts over a
4 s pose change: 0.2°). ``detrend_from_rest`` (a straight line fitted where the rate should be
zero) is what the pairs and the step search use; ``tail_offset`` (from the tail's shape) was
worse in simulation: posture sway and ADC quantisation corrupt the shape. The low-pass
(unity DC gain) does not change integrals.
"""
from __future__ import annotations

import numpy as np

from ..accelerator import kernels
from ..butterworth import butter_sos

sosfilt = kernels("gravcal.core._blockkernels").sosfilt


def highpass_ba(hp_hz: float, fs: float) -> tuple[np.ndarray, np.ndarray]:
    """The board's first-order high-pass as simulated at ``fs`` [Hz]: the simulator's own section
    (signal.butter(1, hp_hz, "highpass", fs=fs) bit for bit, without scipy.signal) as lfilter's (b, a)."""
    if not (0 < hp_hz < fs / 2):
        raise ValueError(f"high-pass corner must lie in (0, fs/2 = {fs / 2} Hz), got {hp_hz}")
    b0, b1, _, _, a1, _ = butter_sos(1, float(hp_hz), "highpass", float(fs))[0]
    return np.array([b0, b1]), np.array([1.0, a1])


class HighPassInverse:
    """Streaming exact inverse of the first-order high-pass (explicit lfilter state ``zi``).

    ``update(y)`` takes conditioned samples minus the reference [counts] (N,) or (N, k) and
    returns the pre-high-pass signal [counts] (rate times the pass-band sensitivity), assuming
    the stream started at rest. ``hp_hz=None`` means no high-pass (DC-coupled gyro): identity.
    """

    def __init__(self, hp_hz: float | None, fs: float):
        self.hp_hz, self.fs = hp_hz, float(fs)
        if hp_hz is None:
            self.b = self.a = None
        else:
            b, a = highpass_ba(hp_hz, fs)
            self.b = np.array([1.0, a[1]]) / b[0]  # numerator of 1/H(z)
            self.a = np.array([1.0, -1.0])  # denominator: the integrator
            # the same filter as one second-order section, for the compiled sosfilt kernel (SciPy's arithmetic, as lfilter's)
            self._sos = np.array([[self.b[0], self.b[1], 0.0, 1.0, -1.0, 0.0]])
        self.zi: np.ndarray | None = None

    def reset(self) -> None:
        self.zi = None

    def update(self, y: np.ndarray) -> np.ndarray:
        y = np.asarray(y, dtype=float)
        if self.b is None:
            return y.copy()
        if self.zi is None:
            self.zi = np.zeros((1,) + y.shape[1:])
        x = np.array(y.reshape(y.shape[0], -1).T, order="C")  # (signals, n), a copy: filtered in place
        zi = np.zeros((x.shape[0], 1, 2))
        zi[:, 0, 0] = self.zi.reshape(-1)
        sosfilt(self._sos, x, zi)
        self.zi = zi[:, 0, 0].reshape(self.zi.shape)
        return x.T.reshape(y.shape)


def reconstruct(y: np.ndarray, hp_hz: float | None, fs: float) -> np.ndarray:
    """One-shot :class:`HighPassInverse` over a segment (conditioned minus reference, counts)."""
    return HighPassInverse(hp_hz, fs).update(y)


def tail_offset(y_rest: np.ndarray, hp_hz: float | None, fs: float) -> np.ndarray:
    """The constant C0 that the inverse adds when started on a high-pass tail.

    y_rest (n,) or (n, k): conditioned samples minus the reference [counts] of a quasi-static
    window, the inverse being started on its first sample. At rest the high-pass output is a
    pure tail A q^n (q the discrete pole), and the exact inverse started with zero state turns
    it into the constant A / b0. A is fitted to the decaying shape only (the bias is known), so
    posture sway (an oscillation) and the start of the next movement at the window's end (where
    q^n has died out) barely move it. Returns (k,) C0 [counts]; zero without a high-pass.
    """
    y = np.asarray(y_rest, dtype=float)
    y2 = y.reshape(y.shape[0], -1)
    if hp_hz is None:
        return np.zeros(y2.shape[1])
    b, a = highpass_ba(hp_hz, fs)
    tail = (-a[1]) ** np.arange(y2.shape[0])
    amp = tail @ y2 / (tail @ tail)
    return amp / b[0]


def detrend_from_rest(x: np.ndarray, rest: np.ndarray) -> tuple[np.ndarray, float]:
    """Remove the straight line fitted to ``x`` on the samples where ``rest`` is True (the two
    quasi-static windows bracketing a rotation, where the true rate is zero).

    x (N,) or (N, k); returns (x minus the line, rms of x about the line on the rest samples).
    """
    x = np.asarray(x, dtype=float)
    rest = np.asarray(rest, dtype=bool)
    n = x.shape[0]
    idx = np.flatnonzero(rest)
    if idx.size < 3:
        raise ValueError("detrend_from_rest: fewer than 3 rest samples")
    s = np.arange(n, dtype=float) / max(n - 1, 1)
    design = np.column_stack([np.ones(idx.size), s[idx]])
    coef, *_ = np.linalg.lstsq(design, x[idx].reshape(idx.size, -1), rcond=None)
    line = np.column_stack([np.ones(n), s]) @ coef
    out = x - line.reshape(x.shape)
    rms = float(np.sqrt(np.mean(out[idx] ** 2)))
    return out, rms
