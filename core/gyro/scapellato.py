"""Scapellato et al. 2005: the gyro sensitivity that makes a step of known height come out right.

The IMU on the foot instep, single gyro axis medio-lateral. For each foot placement from one
tread onto the next (sec. 1-2):

1. the pitch comes from the calibrated accelerometer in stance, f = R_y(theta)^T e_up =
   (-sin theta, ., cos theta) -> theta = atan2(-f_x, f_z), averaged over the first stance;
2. sagittal strapdown: theta(t) = integral of omega from the start of that stance plus the
   constant that matches the accelerometer's pitch over the stance; omega = u / S with u the
   gyro counts above the bias, the board's high-pass undone (``conditioning``) and detrended on
   the two stances; the calibrated specific force (the ADXL210's low-pass undone when its
   corner is given) is projected onto the sagittal directions and gravity removed:
   [a_X, a_Z] = R_y(theta) [f_x, f_z] - e_up  (times g);
3. zero-velocity update: velocity is zero in stance; integrated from the end of one stance it
   must be zero again at the start of the next, so its drift is removed as a ramp over the
   swing; the position integral of the corrected velocity gives the displacement;
4. the sensitivity S minimising sum_k (dZ_k(S) - h)^2 over the placements (scipy.optimize
   bounded scalar minimisation) is the estimate.

Uncertainty: from the residual scatter of the placements and the slope dZ/dS at the optimum
(linearised least squares: var S = s^2 / sum (dZ_k/dS)^2, s^2 = residual variance).
Why it works: a scale error eps rotates the estimated world specific force by eps (theta -
theta0); its vertical part is -eps (theta - theta0) a_X, so the height error is driven by the
correlation of pitch change and forward acceleration during the swing. ZUPT removes the part
of it that is symmetric in time: a pitch excursion that is antisymmetric (plantarflexion then
dorsiflexion) leaves 0.2 mm per 10 % of sensitivity, a one-sided one 4-5 mm (docs/gyro.md).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import optimize
from scipy.integrate import cumulative_simpson

from ..calibration import Calibration
from .conditioning import detrend_from_rest, reconstruct

G = 9.80665


@dataclass
class Placement:
    """One swing with its two stances, ready for strapdown at any sensitivity."""

    u: np.ndarray  # (K,) gyro counts (bias removed, high-pass undone, detrended) from stance to stance
    f: np.ndarray  # (K, 3) calibrated specific force [g] over the same samples
    n_stance: int  # samples of the first stance (at the start of u, f)
    swing: slice  # from the last sample of the first stance to the first sample of the next
    dt: float


def placements(gyro: np.ndarray, acc_raw: np.ndarray, acc_calibration: Calibration, stances: list[tuple[int, int]],
               *, bias: float, fs: float, hp_hz: float | None, acc_lowpass_hz: float | np.ndarray | None = None) -> list[Placement]:
    """Cut a recording into swings between consecutive stances (sample ranges).

    ``acc_lowpass_hz``: the accelerometer's analog low-pass (ADXL210 Cx/Cy pole, 5 µF / C, 10.6 Hz
    on this board). It delays the specific force by ~15 ms against the gyro (whose own 25 Hz
    low-pass delays it by ~6 ms); strapdown multiplies the two, so the mismatch biases the
    height (-1.2 mm per placement in simulation, a ~3 % sensitivity bias). The one-pole filter
    is undone exactly (its matched-z inverse is a 2-tap FIR: x = (y[n] - p y[n-1]) / (1 - p)).
    """
    gyro = np.asarray(gyro, float).reshape(-1)
    out = []
    for (a0, a1), (b0, b1) in zip(stances[:-1], stances[1:]):
        if not (a0 < a1 <= b0 < b1):
            raise ValueError(f"stances must be increasing, non-overlapping sample ranges, got {(a0, a1)}, {(b0, b1)}")
        y = gyro[a0:b1] - bias
        x = reconstruct(y, hp_hz, fs)
        rest = np.zeros(b1 - a0, bool)
        rest[: a1 - a0] = True
        rest[b0 - a0:] = True
        x, _ = detrend_from_rest(x, rest)
        f = acc_calibration.apply(np.asarray(acc_raw[a0:b1], float))
        if acc_lowpass_hz is not None:
            p = np.exp(-2.0 * np.pi * np.asarray(acc_lowpass_hz, float) / fs)  # ADXL210 pole(s) as simulated (matched z)
            f = np.concatenate([f[:1], (f[1:] - p * f[:-1]) / (1.0 - p)])
        out.append(Placement(x, f, a1 - a0, slice(a1 - a0 - 1, b0 - a0 + 1), 1.0 / fs))
    return out


def displacement(p: Placement, sensitivity: float) -> tuple[float, float]:
    """(dX, dZ) [m] of one swing by sagittal strapdown with ZUPT at gyro ``sensitivity``
    [counts per rad/s]. The pitch is integrated from the start of the first stance; its
    constant is set so that, over that stance, it matches the accelerometer's pitch on
    average (a pitch error d at the end of the stance would tilt the whole displacement
    vector: a height error -d dX, 0.3 mm per mrad on a 28 cm tread)."""
    theta = cumulative_simpson(p.u / sensitivity, dx=p.dt, initial=0.0)
    st = p.f[: p.n_stance]
    theta_acc = np.arctan2(-st[:, 0], st[:, 2])
    theta = theta + np.mean(theta_acc - theta[: p.n_stance])
    theta, f = theta[p.swing], p.f[p.swing]
    c, s = np.cos(theta), np.sin(theta)
    a_x = (c * f[:, 0] + s * f[:, 2]) * G  # R_y(theta) f: world forward
    a_z = (-s * f[:, 0] + c * f[:, 2] - 1.0) * G  # world up, gravity removed
    v = np.column_stack([cumulative_simpson(a_x, dx=p.dt, initial=0.0), cumulative_simpson(a_z, dx=p.dt, initial=0.0)])
    ramp = np.linspace(0.0, 1.0, v.shape[0])[:, None]
    v = v - ramp * v[-1]  # ZUPT: zero velocity in both stances
    pos = cumulative_simpson(v, dx=p.dt, axis=0, initial=0.0)
    return float(pos[-1, 0]), float(pos[-1, 1])


@dataclass
class StepSearchResult:
    sensitivity: float  # [counts per rad/s]
    std: float  # [counts per rad/s]
    heights_m: np.ndarray  # estimated height of each placement at the optimum
    rms_error_m: float
    n_placements: int
    slope_m_per_count: float  # mean dZ/dS at the optimum [m per (counts per rad/s)]


def step_height_search(places: list[Placement], step_height_m: float | None, *, start: float,
                       bounds_rel: tuple[float, float] = (0.5, 2.0)) -> StepSearchResult:
    """Scapellato's search: the sensitivity [counts per rad/s] for which the strapdown heights
    of the placements match the known step height [m]. ``start`` sets the search interval
    (start * bounds_rel)."""
    if step_height_m is None or not np.isfinite(step_height_m):
        raise ValueError("step height unknown: Scapellato's method needs the true height of the steps [m]")
    if step_height_m <= 0:
        raise ValueError(f"step height must be positive (a climb onto a step), got {step_height_m} m: "
                         "on level ground the height carries no information on the gyro sensitivity")
    if len(places) < 2:
        raise ValueError(f"need at least 2 foot placements between stances, got {len(places)}")
    if not (start > 0 and np.isfinite(start)):
        raise ValueError(f"start sensitivity must be positive, got {start}")
    bad = [k for k, p in enumerate(places) if not (np.all(np.isfinite(p.u)) and np.all(np.isfinite(p.f)))]
    if bad:  # a NaN height makes the search's cost NaN: it would end anywhere, with no error
        raise ValueError(f"foot placement(s) {bad} hold NaN/inf gyro or accelerometer samples: no height from them")

    def heights(s: float) -> np.ndarray:
        return np.array([displacement(p, s)[1] for p in places])

    def cost(s: float) -> float:
        return float(np.sum((heights(s) - step_height_m) ** 2))

    lo, hi = start * bounds_rel[0], start * bounds_rel[1]
    res = optimize.minimize_scalar(cost, bounds=(lo, hi), method="bounded", options={"xatol": start * 1e-6})
    s_hat = float(res.x)
    hz = heights(s_hat)
    h = s_hat * 1e-3
    slope = (heights(s_hat + h) - heights(s_hat - h)) / (2 * h)
    n = len(places)
    resid = hz - step_height_m
    if not np.any(np.abs(slope) > 0):
        raise ValueError("the strapdown height does not depend on the gyro sensitivity for these placements: no estimate")
    s2 = float(resid @ resid) / max(n - 1, 1)
    std = float(np.sqrt(s2 / (slope @ slope)))
    at_bound = min(s_hat - lo, hi - s_hat) < 1e-3 * start
    if at_bound:
        raise ValueError(f"step-height search ended at the edge of [{lo:.4g}, {hi:.4g}] counts per rad/s: "
                         "no sensitivity in range makes the heights match (wrong step height or start?)")
    return StepSearchResult(s_hat, std, hz, float(np.sqrt(np.mean(resid**2))), n, float(np.mean(slope)))
