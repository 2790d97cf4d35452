"""The thermal-lag term: its lag against the closed-form step response, block-split invariance of the
simulator, and a calibration that carries the term correcting samples at their own temperature history."""
from __future__ import annotations

import numpy as np

from gravcal.core.model.base import Context
from gravcal.core.model.lag import first_order_lag
from gravcal.core.model.terms import REGISTRY


def lag_term(coef, tau_s):
    return REGISTRY["thermal_lag"].forward(coef_g_per_c=coef, t0_c=25.0, tau_s=tau_s)


def test_lag_follows_a_step_with_its_time_constant():
    """A temperature step of 10 °C at t = 0: T_lag = 10 (1 - exp(-t / tau)), windows in any order."""
    rng = np.random.default_rng(3)
    for tau in (30.0, 300.0, 2000.0):
        t = np.sort(rng.uniform(0.0, 3 * tau, 200))
        t[0] = 0.0
        x = np.where(t > 0, 10.0, 0.0)
        perm = rng.permutation(t.size)
        y = first_order_lag(t[perm], x[perm], tau)
        # each value holds over the interval ending at its time: the exact response to a step at t = 0+
        expected = 10.0 * (1.0 - np.exp(-t[perm] / tau))
        assert np.allclose(y, expected, atol=1e-9), tau


def test_simulated_lag_is_block_split_invariant_and_matches_the_helper():
    fs, n = 50.0, 6000
    t = np.arange(n) / fs
    temp = 25.0 + 8.0 * np.sin(t / 40.0)
    coef = np.array([2e-3, -1e-3, 1.5e-3, 2e-3])
    whole = lag_term(coef, 20.0).forward(np.zeros((n, 4)), Context(t, temp, np.full(n, 3.3), fs))
    split_term = lag_term(coef, 20.0)
    parts = [split_term.forward(np.zeros((k, 4)), Context(t[a:a + k], temp[a:a + k], np.full(k, 3.3), fs))
             for a, k in ((0, 1234), (1234, 4766))]
    assert np.allclose(np.vstack(parts), whole, rtol=0, atol=1e-12)
    lag = first_order_lag(t, temp, 20.0)
    assert np.allclose(whole, np.outer(lag - 25.0, coef), atol=1e-9)
    assert np.max(np.abs(lag - temp)) > 1.0  # the lag is not the temperature itself at this tau


def test_linear_part_is_the_forward_offset():
    fs, n = 10.0, 3000
    t = np.arange(n) / fs
    temp = 20.0 + 0.01 * t
    coef = np.array([1e-3, 2e-3, -3e-3, 1e-3])
    term = lag_term(coef, 100.0)
    ctx = Context(t, temp, np.full(n, 3.3), fs)
    gain, off = term.linear_part(ctx)
    fwd = lag_term(coef, 100.0).forward(np.zeros((n, 4)), ctx)
    assert np.allclose(gain, 1.0) and np.allclose(off, fwd, atol=1e-9)
