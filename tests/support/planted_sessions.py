"""Window-level sessions written from the physics, independent of gravcal's simulator (core/diagnosis/synthetic.py
and core/model): the diagnose tests judge diagnose on data it did not shape.

A triaxial accelerometer in counts (its own scale: 1024 counts/g, zero-g near 2048), worn through an hour of
quasi-static moments. Each window mean is

    raw = o + d(T, t) + K (u + w) + e,

u the unit gravity direction in the sensor frame, K = diag(s) (I + small cross-axis terms), o the zero-g level,
d the planted offset disturbance [counts] (a function of the window's temperature T and time t), w the body's
residual motion (~``floor_g`` along gravity), e the white noise of a mean over n samples. Every random draw
comes from this module's own numpy Generator streams, seeded by (seed, purpose).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from gravcal.core.calibration import Calibration
from gravcal.core.windows import WindowSet

COUNTS_PER_G = 1024.0
ZERO_G = 2048.0
NOISE_G = 2.5e-3  # per-sample white noise [g] at the session's sample rate
FS = 50.0


@dataclass
class Planted:
    ws: WindowSet
    start: Calibration  # a start 1 % off the truth, as a datasheet start would be
    sens: np.ndarray  # (3,) true counts per g
    offset: np.ndarray  # (3,) true zero-g level [counts] at the reference
    disturbance_g: np.ndarray  # (m, 3) the planted offset disturbance [g]
    info: dict[str, Any] = field(default_factory=dict)


def _rng(seed: int, purpose: int) -> np.random.Generator:
    return np.random.default_rng([20_261_207, seed, purpose])


def postures(rng: np.random.Generator, m: int, kind: str = "daily") -> np.ndarray:
    """Unit gravity directions: ``daily`` (upright with tilts, reclined, lying on back/front/sides) or
    ``single`` (one resting pose, set down again between moments: 0.3° apart)."""
    if kind == "single":
        base = np.tile([0.05, -0.03, 1.0], (m, 1))
        v = base + rng.normal(0, 0.005, (m, 3))
    else:
        anchors = np.array([[0, 0, 1.0], [0.6, 0, 0.8], [1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0],
                            [0.3, 0.3, 0.9]])
        pick = rng.choice(len(anchors), size=m, p=[0.4, 0.15, 0.1, 0.1, 0.08, 0.07, 0.1])
        v = anchors[pick] + rng.normal(0, 0.12, (m, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def temperature_profile(rng: np.random.Generator, t: np.ndarray, kind: str, duration: float) -> np.ndarray:
    """Window temperatures [°C]: ``ramp`` a monotone warm-up 21 -> 33 °C over the session (settling),
    ``linear_ramp`` the same at a constant rate (temperature and time collinear); ``body`` skin-warmed
    with two cool spells (22-34 °C); ``cycle`` a slow back-and-forth 22 <-> 34 °C (a lag shows in it)."""
    x = t / duration
    if kind == "ramp":
        T = 21.0 + 12.0 * (1 - np.exp(-3.0 * x)) / (1 - np.exp(-3.0))
    elif kind == "linear_ramp":
        T = 21.0 + 12.0 * x
    elif kind == "cycle":
        T = 28.0 - 6.0 * np.cos(2 * np.pi * 1.5 * x + rng.uniform(-0.3, 0.3))
    else:
        T = 33.0 - 9.0 * np.exp(-((x - 0.3) / 0.08) ** 2) - 7.0 * np.exp(-((x - 0.75) / 0.1) ** 2)
    return T + rng.normal(0, 0.1, t.size)


def lagged(t: np.ndarray, T: np.ndarray, tau_s: float) -> np.ndarray:
    """The die temperature: the recorded one through dy/dt = (T - y)/tau, integrated on a 1 s grid between
    the windows (the temperature varies between windows too; linearly interpolated)."""
    grid = np.arange(t.min() - 3 * tau_s, t.max() + 1.0, 1.0)
    Tg = np.interp(grid, t, T)
    y = np.empty_like(Tg)
    a = np.exp(-1.0 / tau_s)
    y[0] = Tg[0]
    for i in range(1, Tg.size):
        y[i] = a * y[i - 1] + (1 - a) * Tg[i]
    return np.interp(t, grid, y)


def session(seed: int, disturbance: Callable[[np.ndarray, np.ndarray, np.random.Generator], np.ndarray] | None = None,
            *, temp: str = "body", pose: str = "daily", duration: float = 3600.0, m: int = 160,
            floor_g: float = 0.8e-3) -> Planted:
    """One session; ``disturbance(t, T, rng)`` -> (m, 3) planted offset [g] (None: a clean control)."""
    geo, noise, dist_rng = _rng(seed, 1), _rng(seed, 2), _rng(seed, 3)
    t = np.sort(geo.uniform(0, duration, m))
    n = np.round(FS * geo.uniform(3.0, 15.0, m))
    T = temperature_profile(geo, t, temp, duration)
    v = 3.3 - 0.15 * np.abs(np.sin(np.pi * t / duration * 1.7 + geo.uniform(0, 3))) + geo.normal(0, 0.004, m)
    u = postures(geo, m, pose)
    sens = COUNTS_PER_G * (1 + geo.normal(0, 0.02, 3))
    cross = np.triu(geo.normal(0, 2e-3, (3, 3)), 1)
    K = np.diag(sens) @ (np.eye(3) + cross)
    offset = ZERO_G + geo.normal(0, 15.0, 3)
    d_g = np.zeros((m, 3)) if disturbance is None else np.asarray(disturbance(t, T, dist_rng), dtype=float)
    w = noise.normal(0, floor_g, m)[:, None] * u  # residual motion along gravity
    e = noise.normal(0, NOISE_G, (m, 3)) / np.sqrt(n)[:, None]
    mean = offset + d_g * sens + (u + w) @ K.T + e * sens
    cov = np.broadcast_to(np.diag((NOISE_G * sens) ** 2), (m, 3, 3)).copy()
    starts = np.round(t * FS).astype(np.int64)
    ws = WindowSet(mean, cov, n, t, np.column_stack([T, v]), starts, starts + n.astype(np.int64))
    start_rng = _rng(seed, 4)
    start = Calibration("start", offset + start_rng.normal(0, 0.01, 3) * sens,
                        np.diag(sens * (1 + start_rng.normal(0, 0.01, 3))))
    return Planted(ws, start, sens, offset, d_g, {"temp": temp, "pose": pose})


def signs(rng: np.random.Generator, scale: float) -> np.ndarray:
    """Per axis: random sign x U(1, 2) x scale."""
    return np.where(rng.random(3) < 0.5, -1.0, 1.0) * rng.uniform(1.0, 2.0, 3) * scale


def quadratic_temperature(lo_g: float = 0.1e-3, hi_g: float = 0.25e-3, t_ref: float = 27.0):
    """Offset c2 (T - t_ref)^2 on every axis, |c2| ~ U(lo, hi) [g/°C²] with a random sign per axis."""
    def d(t, T, rng):
        c = np.where(rng.random(3) < 0.5, -1.0, 1.0) * rng.uniform(lo_g, hi_g, 3)
        return np.outer((T - t_ref) ** 2, c)
    return d


def thermal_lag(coef_g: float, tau_s: float, t_ref: float = 27.0):
    """Offset coef (T_die - t_ref), the die following the recorded temperature through tau_s."""
    def d(t, T, rng):
        return np.outer(lagged(t, T, tau_s) - t_ref, signs(rng, coef_g))
    return d


def random_walk(g_per_sqrt_h: float):
    """Bias random walk [g/sqrt(h)] on every axis."""
    def d(t, T, rng):
        dt_h = np.diff(t, prepend=t[0]) / 3600.0
        return np.cumsum(rng.normal(0, 1, (t.size, 3)) * np.sqrt(dt_h)[:, None], axis=0) * g_per_sqrt_h
    return d


def temperature_and_drift(coef_g: float, rate_g_per_h: float, t_ref: float = 27.0):
    """A linear temperature offset plus a linear offset drift."""
    def d(t, T, rng):
        return np.outer(T - t_ref, signs(rng, coef_g)) + np.outer(t / 3600.0, signs(rng, rate_g_per_h))
    return d


def linear_temperature(coef_g: float, t_ref: float = 27.0):
    def d(t, T, rng):
        return np.outer(T - t_ref, signs(rng, coef_g))
    return d
