"""Gyro bias from quasi-static windows (recursive, with uncertainty), and the gyro's
confirmation that a window the accelerometer's detector found is really still.

Which bias. On the ENC-03J board the sensor voltage V0 + Sv w is high-passed before the
amplifier, so at zero rate the ADC reads the conditioning stage's reference (vref_ratio of
the supply, ratiometric to the ADC: a fixed number of counts, plus the op-amp offset), NOT the
sensor's null V0: V0 and its temperature drift are removed by the high-pass. What the high-pass
leaves after a movement is a tail y = b + A q^n (q = the discrete pole, tau = 1/(2 pi f_hp) =
0.53 s), so a window that starts shortly after a rotation is fitted with that tail instead of
a plain mean; the tail's time constant is the board's, known. For a DC-coupled triaxial gyro
(hp_hz None) the window mean is the bias.

Uncertainty of a window's bias: the residual splits into white noise (its variance from first
differences; averages down with the sample count) and slow motion (posture sway, whose window
mean is about as large as its rms; it averages down only with the number of independent
stretches, T * 2 * SWAY_BANDWIDTH_HZ). On simulated Lötters sessions with a triaxial gyro, the
white-noise-only uncertainty gave bias errors up to 3.5 sigma; with this split, within 2.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .conditioning import highpass_ba

SWAY_BANDWIDTH_HZ = 0.5  # posture sway band (standing/sitting: 0.1-0.6 Hz)
BIAS_FLOOR_RAD_S = 1e-3  # 0.06 °/s: undetectable slow rotation in a "still" window (simulated turn ends: up to 0.05 °/s)


def require_finite(y: np.ndarray, what: str) -> np.ndarray:
    """``y`` as floats; ValueError naming how many of its gyro samples are NaN/inf: neither a window's bias fit
    (LAPACK's least squares) nor a pose change's integration can use one."""
    y = np.asarray(y, dtype=float)
    bad = int(y.size - np.count_nonzero(np.isfinite(y)))
    if bad:
        raise ValueError(f"{bad} of the {y.size} gyro values {what} are NaN/inf")
    return y


@dataclass
class WindowBias:
    bias: np.ndarray  # (k,) [counts]
    var: np.ndarray  # (k,) variance of bias [counts^2]
    rms: np.ndarray  # (k,) rms of the samples about the fit [counts] (noise + residual motion)
    n: int


def window_bias(y: np.ndarray, fs: float, hp_hz: float | None = None, floor: float | np.ndarray = 0.0) -> WindowBias:
    """Bias of one quasi-static window's gyro samples y (n,) or (n, k) [counts].

    ``floor`` [counts]: a std added to every window's bias: a slow steady rotation (the end of
    a minimum-jerk pose change, a drifting posture) looks exactly like a bias offset and no
    noise analysis can see it; ``calibrate_gyro`` uses BIAS_FLOOR_RAD_S times the rate scale.
    """
    y = require_finite(y, "of a quasi-static window")
    y2 = y.reshape(y.shape[0], -1)
    n, k = y2.shape
    if n < 4:
        raise ValueError(f"window too short for a gyro bias: {n} samples")
    if hp_hz is None:
        design = np.ones((n, 1))
    else:
        _, a = highpass_ba(hp_hz, fs)
        design = np.column_stack([np.ones(n), (-a[1]) ** np.arange(n)])  # b + A q^n: the high-pass tail
    coef, *_ = np.linalg.lstsq(design, y2, rcond=None)
    res = y2 - design @ coef
    dof = max(n - design.shape[1], 1)
    s2 = (res**2).sum(axis=0) / dof
    # two parts: white noise (from first differences) averages down with n; the rest is slow
    # motion (posture sway, 0.2-0.6 Hz), whose window mean is ~ as large as its rms: it averages
    # down only with the number of ~1 s stretches in the window (bandwidth ~0.5 Hz -> T * 2B).
    white = np.diff(res, axis=0).var(axis=0) / 2.0
    slow = np.clip(s2 - white, 0.0, None)
    cov00 = np.linalg.inv(design.T @ design)[0, 0]
    var = white * cov00 + slow / max(1.0, n / fs * 2.0 * SWAY_BANDWIDTH_HZ) + np.asarray(floor, float) ** 2
    return WindowBias(coef[0], var, np.sqrt(s2), n)


@dataclass
class GyroBiasEstimator:
    """Recursive bias (scalar Kalman filter per axis) over quasi-static windows.

    State: bias [counts] with variance; between windows the bias may wander as a random walk
    of ``walk_counts_per_sqrt_s`` (0: constant bias). A window whose bias is more than
    ``gate_sigma`` away from the prediction is rejected (it was probably not still) once
    ``min_windows`` have been accepted.
    """

    k: int = 1
    walk_counts_per_sqrt_s: float = 0.0
    gate_sigma: float = 6.0
    min_windows: int = 3
    bias: np.ndarray = field(init=False)
    var: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.bias = np.full(self.k, np.nan)
        self.var = np.full(self.k, np.inf)
        self.t_last: float | None = None
        self.n_windows = 0
        self.n_rejected = 0
        self.noise_rms = np.full(self.k, np.nan)  # rms about the fit of the last accepted window
        self._chi2 = np.zeros(self.k)  # sum of normalised innovations^2 (window-to-window consistency)
        self._first: list[tuple[np.ndarray, np.ndarray]] = []

    def update(self, wb: WindowBias, t: float) -> bool:
        """Fold in one window's bias at time t [s]; returns whether it was accepted.

        Start: the first ``min_windows`` windows are combined at their median (one window with a
        slow rotation in it must not become the reference that rejects the good ones)."""
        b = np.asarray(wb.bias, float).reshape(self.k)
        v = np.asarray(wb.var, float).reshape(self.k)
        if self.n_windows < self.min_windows:
            self._first.append((b, v))
            bs = np.array([x[0] for x in self._first])
            vs = np.array([x[1] for x in self._first])
            self.bias = np.median(bs, axis=0)
            self.var = 1.0 / np.sum(1.0 / vs, axis=0) * (np.pi / 2 if len(bs) > 2 else 1.0)  # median's efficiency
        else:
            dt = 0.0 if self.t_last is None else max(float(t) - self.t_last, 0.0)
            var_pred = self.var + self.walk_counts_per_sqrt_s**2 * dt
            innov = b - self.bias
            s = var_pred + v
            if self.n_windows >= self.min_windows and np.any(innov**2 > self.gate_sigma**2 * s):
                self.n_rejected += 1
                return False
            self._chi2 += innov**2 / s
            gain = var_pred / s
            self.bias = self.bias + gain * innov
            self.var = (1 - gain) * var_pred
        self.t_last = float(t)
        self.noise_rms = np.asarray(wb.rms, float).reshape(self.k)
        self.n_windows += 1
        return True

    @property
    def std(self) -> np.ndarray:
        """Bias std [counts], inflated by the windows' reduced chi2 when it exceeds 1: window
        means also carry residual motion (sway) that the per-window noise model does not."""
        dof = self.n_windows - self.min_windows
        f = np.maximum(1.0, self._chi2 / dof) if dof >= 2 else np.ones(self.k)
        return np.sqrt(self.var * f)


@dataclass
class GyroStillnessGate:
    """Confirms, with the gyro, that a window found by the accelerometer's detector is still.

    A window is confirmed when the rms rate of its samples, after the bias (and, with a
    high-pass, its tail) is removed, is below ``threshold_rad_s`` on every axis. The rate scale
    ``counts_per_rad_s`` may be nominal (a 20 % error moves the threshold by 20 %).
    Default 0.05 rad/s (2.9 °/s rms): the ENC-03J's noise is ~0.3 °/s rms and standing sway
    ~1-2 °/s, a slow posture change 10-100 °/s. Limitation of the high-pass board: a rotation
    at constant rate lasting the whole window is a step the high-pass turns into a decaying
    tail, which the fit absorbs; such windows are caught by the accelerometer (the window's
    direction spread, ``core.pipeline.screen_windows``).
    """

    fs: float
    counts_per_rad_s: float | np.ndarray
    hp_hz: float | None = None
    threshold_rad_s: float = 0.05

    def rate_rms(self, y: np.ndarray) -> np.ndarray:
        """(k,) rms rate [rad/s] of a window's gyro samples y (n,) or (n, k) [counts]."""
        wb = window_bias(y, self.fs, self.hp_hz)
        return wb.rms / np.abs(np.asarray(self.counts_per_rad_s, float))

    def confirm(self, y: np.ndarray) -> tuple[bool, float]:
        """(still?, largest rms rate over the axes [rad/s])."""
        r = float(np.max(self.rate_rms(y)))
        return r < self.threshold_rad_s, r
