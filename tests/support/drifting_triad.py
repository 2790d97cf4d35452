"""A drifting triad worn for a day and a half, written here from the physics (not gravcal's simulator): its
three offsets and three sensitivities each drift linearly at their own random rate (up to 2 mg/h and 0.05 %/h,
the offsets' and sensitivities' scale of a body-worn ADXL210), turned to a new random posture every 20
minutes, one 10 s window (2000 samples of 3 mg white noise per axis) every 2 minutes, each window off by a
small sway of its direction and a per-window error of FLOOR_G [g] per axis (residual motion, model error)
beyond its samples' noise. Own numpy stream (default_rng([seed, 2026])); only gravcal's Calibration container.

Used by tests/core/test_adaptive_walk.py and test_adaptive_floor.py (the online recursion's adapted walk and
floor against the truth)."""
from __future__ import annotations

import math

import numpy as np

from gravcal.core.calibration import Calibration

HOURS = 36
FLOOR_G = 5e-4  # per-window error beyond the samples' noise (model error, sway) [g]
SCALE = 0.04  # raw per g
NAMES = ("s_x", "s_y", "s_z", "o_x", "o_y", "o_z")


def drifting_triad(seed: int, hours: float = HOURS):
    """(t, means, covariance of the mean (one for all windows), truth(t) -> the 6 parameters, start) of one session;
    the start is 20 mg / 1 % off the truth at t = 0."""
    rng = np.random.default_rng([seed, 2026])
    s0 = SCALE * (1 + 0.05 * rng.normal(size=3))
    o0 = 0.5 + 0.02 * rng.normal(size=3)
    vs = s0 * rng.uniform(-5e-4, 5e-4, 3) / 3600.0  # up to 0.05 %/h
    vo = SCALE * rng.uniform(-2e-3, 2e-3, 3) / 3600.0  # up to 2 mg/h
    t = np.arange(120.0, hours * 3600.0 + 1, 120.0)
    seg = (t // 1200).astype(int)
    dirs = rng.normal(size=(seg.max() + 1, 3))
    f = dirs[seg] + 0.02 * rng.normal(size=(len(t), 3))  # small sway within a posture
    f /= np.linalg.norm(f, axis=1, keepdims=True)  # quasi-static: |f| = 1 g
    s, o = s0 + np.outer(t, vs), o0 + np.outer(t, vo)
    n = 2000
    sd = 3e-3 * s0 / math.sqrt(n)  # std of a window mean per axis [raw]
    means = s * f + o + sd * rng.normal(size=(len(t), 3)) + FLOOR_G * s0 * rng.normal(size=(len(t), 3))
    cm = np.diag(sd**2)

    def truth(tt: float) -> np.ndarray:
        return np.concatenate([s0 + tt * vs, o0 + tt * vo])

    start = Calibration("6", o0 + SCALE * 0.02 * rng.choice([-1, 1], 3), np.diag(s0 * (1 + 0.01 * rng.choice([-1, 1], 3))))
    return t, means, cm, truth, start
