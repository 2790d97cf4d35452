"""The online recursion's adapted random walk (core/estimators/adaptive_walk.py) states std that cover a
drifting truth, per parameter, on windows from a generator written here from the physics (not the project's
simulator): a triad whose three offsets and three sensitivities each drift linearly at their own random
rate (up to 2 mg/h and 0.05 %/h, the offsets' and sensitivities' scale of a body-worn ADXL210), turned to a
new random posture every 20 minutes, one 10 s window (2000 samples of 3 mg white noise per axis) a minute.

The recursion starts 20 mg / 1 % off with one configured walk for all (3e-12 raw²/s: the offsets' 2.6
mg/sqrt(h) at 0.04 raw/g, the sensitivities 1/16 of it), far from most parameters' drift, and the windows'
error as its floor. Every 4 h from hour 20 on each parameter's error over its stated std is a z; checks 4 h
apart are nearly independent (the filter's memory is about an hour). SEEDS x CHECKS x 6 = 1200 values:
- not over-confident: mean z² <= 1 + 3 sqrt(2 / n) (the std of a mean of n chi²_1 / n is sqrt(2 / n)),
  pooled (n = 1200) and per parameter (n = 200);
- the issue's band for the share within 1σ, 60-76 % (its binomial std at n = 1200 is 1.3 %).
Measured: RMS z 0.84 (per parameter 0.71-0.91), 75.2 % within 1σ: conservative, the walk the test
pushes up for a linear drift is the one for the block's length (1 h), longer than the filter's memory
here. Left at its configured value: 79.2 % within 1σ (RMS z 0.65 for the offsets): red. A std scaled by 0.7
fails the first bound, by 1.4 the band (checked).
"""
from __future__ import annotations

import math

import numpy as np

from gravcal.core.calibration import Calibration
from gravcal.core.estimators.adaptive_walk import AdaptiveWalk, drift_walk
from gravcal.core.estimators.recursive import LottersRecursive

SEEDS, HOURS, CHECK_H, FIRST_H = 40, 36, 4, 20
FLOOR_G = 5e-4  # per-window error beyond the samples' noise (model error, sway) [g], known to the recursion
Q0 = 3e-12
SCALE = 0.04  # raw per g
NAMES = ("s_x", "s_y", "s_z", "o_x", "o_y", "o_z")


def drifting_triad(seed: int):
    """(t, means, covariances of the mean, truth(t) -> 6 parameters) of one session."""
    rng = np.random.default_rng([seed, 2026])
    s0 = SCALE * (1 + 0.05 * rng.normal(size=3))
    o0 = 0.5 + 0.02 * rng.normal(size=3)
    vs = s0 * rng.uniform(-5e-4, 5e-4, 3) / 3600.0  # up to 0.05 %/h
    vo = SCALE * rng.uniform(-2e-3, 2e-3, 3) / 3600.0  # up to 2 mg/h
    t = np.arange(120.0, HOURS * 3600.0 + 1, 120.0)
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


def session_z(seed: int, adapt: bool = True) -> np.ndarray:
    """(checks, 6) errors over the stated std at every CHECK_H from FIRST_H."""
    t, means, cm, truth, start = drifting_triad(seed)
    rec = LottersRecursive(start, "6", sigma_floor_g=FLOOR_G, process_noise=drift_walk(list(NAMES), Q0))
    assert tuple(rec.names) == NAMES
    walk = AdaptiveWalk(Q0)
    walk.attach(rec)
    zs, next_h = [], FIRST_H
    for k in range(len(t)):
        if rec.step(means[k], cm, float(t[k])) and adapt:
            walk.observe(rec, means[k], cm)
        if t[k] >= next_h * 3600.0:
            zs.append((rec.p - truth(float(t[k]))) / np.sqrt(np.diag(rec.P)))
            next_h += CHECK_H
    return np.array(zs)


def test_the_adapted_walk_states_std_that_cover_each_drifting_parameter():
    z = np.concatenate([session_z(seed) for seed in range(SEEDS)])
    assert z.shape == (SEEDS * (1 + (HOURS - FIRST_H) // CHECK_H), 6), z.shape
    z2 = z * z
    assert z2.mean() <= 1 + 3 * math.sqrt(2 / z.size), (np.sqrt(z2.mean()), np.sqrt(z2.mean(axis=0)))
    per = z2.mean(axis=0)
    assert np.all(per <= 1 + 3 * math.sqrt(2 / z.shape[0])), dict(zip(NAMES, np.sqrt(per).round(2)))
    within = float(np.mean(np.abs(z) <= 1))
    assert 0.60 <= within <= 0.76, (within, dict(zip(NAMES, np.sqrt(per).round(2))))
