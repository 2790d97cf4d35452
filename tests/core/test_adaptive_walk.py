"""The online recursion's adapted random walk (core/estimators/adaptive_walk.py) states std that cover a
drifting truth, per parameter, on windows from a generator written from the physics (not the project's
simulator, tests/support/drifting_triad.py): a triad whose three offsets and three sensitivities each drift
linearly at their own random rate (up to 2 mg/h and 0.05 %/h), turned to a new random posture every 20
minutes, one 10 s window (2000 samples of 3 mg white noise per axis) every 2 minutes.

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
from support.drifting_triad import FLOOR_G, HOURS, NAMES, drifting_triad

from gravcal.core.estimators.adaptive_walk import AdaptiveWalk, drift_walk
from gravcal.core.estimators.recursive import LottersRecursive

SEEDS, CHECK_H, FIRST_H = 40, 4, 20
Q0 = 3e-12


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
