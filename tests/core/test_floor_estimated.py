"""The std of a batch fit whose quasi-static floor is estimated from its own residuals, on sessions gravcal's
simulator did not make (tests/support/independent_sessions.py): the floor is the one of the fit it weights,
and the stated variance is, on average, the one the true floor would give (Student t's widening included).
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from seed_pool import pmap

from gravcal.core.estimators.lotters import FLOOR_RTOL, LottersBatch, floor_t_factor
from gravcal.core.estimators.start import ellipsoid_fit

from tests.support.independent_sessions import session

PARAMS = [f"o_{a}" for a in "xyz"] + [f"s_{a}" for a in "xyz"]
TRUE_FLOOR_G = 0.002  # the generator's residual body motion per axis (session's floor_g default)
M_SHORT = 30  # windows: few residual dof (24), so the estimated floor's spread is large enough to measure


def variance_ratio(seed: int) -> float | None:
    """The mean over o, s of (std with the true floor / stated std)² of one session (None: not determined); the
    true-floor std without the Birge inflation (which only ever widens it). Both fits start from the ellipsoid
    fit of the windows, as a fit without a start does: computed once, it is the same start."""
    ws = session("six", seed, m=M_SHORT).windows
    try:
        start = ellipsoid_fit(ws)
        est = LottersBatch("6").fit(ws, start)
        ref = LottersBatch("6", sigma_floor_g=TRUE_FLOOR_G).fit(ws, start)
    except ValueError:
        return None
    if not (est.converged and ref.converged) or max(est.metadata["std_g"].values()) > 0.03:
        return None
    ref_var = np.array([ref.std[n] ** 2 for n in PARAMS]) / ref.metadata["cov_inflation"]
    return float(np.mean(ref_var / np.array([est.std[n] ** 2 for n in PARAMS])))


@pytest.fixture(scope="module")
def variance_ratios() -> np.ndarray:
    return np.array([r for r in pmap(variance_ratio, [(s,) for s in range(400)]) if r is not None])


def test_stated_variance_is_on_average_the_true_floors(variance_ratios):
    """Dividing by an estimated std makes the error Student t: without the widening the stated variance is
    ~6 % short of the true floor's here (dof 24); with it the mean ratio is 1 within 3 standard errors."""
    r = variance_ratios
    assert r.size >= 300, f"only {r.size} of 400 sessions determined"
    se = r.std(ddof=1) / math.sqrt(r.size)
    assert abs(r.mean() - 1.0) < 3 * se, f"mean (true-floor std / stated std)² = {r.mean():.4f} ± {se:.4f}"


@pytest.mark.parametrize("kind", ["six", "misaligned_lab"])
def test_the_floor_is_the_one_of_the_fit_it_weights(kind):
    """The floor solves sum r²/(v + f²) = m - P at the residuals of the fit weighted with it: the reported
    reduced chi² is 1 to the floor's settling tolerance (a floor solved once, from the fit weighted by the
    windows' noise alone, leaves it 0.5-2 % below 1)."""
    for seed in range(20):
        cal = LottersBatch("6" if kind == "six" else "6+misalignment").fit(session(kind, seed).windows)
        if cal.metadata["reduced_chi2_window_noise_only"] <= 1.0:
            continue
        assert abs(cal.metadata["reduced_chi2"] - 1.0) < FLOOR_RTOL / 2, (seed, cal.metadata["reduced_chi2"])


def test_t_factor_limits():
    """Floor alone (window noise 0): every parameter's variance widens by dof / (dof - 2); no floor: by nothing;
    window noise far above the floor: by almost nothing."""
    rng = np.random.default_rng(5)
    B = rng.normal(size=(40, 6))
    dof = 40 - 6
    f2 = 4e-6
    for v, lo, hi in ((np.full(40, 1e-30), dof / (dof - 2), dof / (dof - 2)), (np.full(40, 1e-2), 1.0, 1.0 + 1e-3)):
        var = v + f2
        cov = np.linalg.inv((B.T / var) @ B)
        g = floor_t_factor(B, var, cov, f2, dof) ** 2
        assert np.all(g >= lo * (1 - 1e-9)) and np.all(g <= hi * (1 + 1e-9)), g
    assert np.all(floor_t_factor(B, np.full(40, 1e-6), np.eye(6), 0.0, dof) == 1.0)


def test_t_factor_between_its_limits_when_the_floor_is_half_the_variance():
    """Window noise equal to the floor: each determined parameter widens by less than the floor-alone factor
    and more than none; a direction two collinear columns leave undetermined (its variance is the guard's,
    independent of f²) is not widened, and nothing is NaN."""
    rng = np.random.default_rng(2)
    B = rng.normal(size=(30, 6))
    B[:, 5] = B[:, 4]
    var = np.full(30, 2e-6)
    lam, V = np.linalg.eigh((B.T / var) @ B)
    cov = (V / np.maximum(lam, 1e-15 * lam[-1])) @ V.T
    g = floor_t_factor(B, var, cov, 1e-6, 24) ** 2
    assert np.all(np.isfinite(g))
    assert np.all((g[:4] > 1.0 + 1e-3) & (g[:4] < 24 / 22 - 1e-3)), g
    assert np.allclose(g[4:], 1.0, atol=1e-9), g
