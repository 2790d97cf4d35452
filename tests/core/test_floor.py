"""The quasi-static floor solve (core.estimators.floor) against scipy.optimize.brentq and its equation."""
import numpy as np
import pytest
from scipy.optimize import brentq

from gravcal.core.estimators.floor import quasi_static_floor

TINY = 1e-14


def _case(seed: int) -> tuple[np.ndarray, np.ndarray, int]:
    rng = np.random.default_rng(seed)
    m = int(rng.integers(20, 4000))
    var = rng.uniform(1e-9, 1e-7, m) * 10 ** rng.uniform(-2, 2)
    extra = rng.uniform(0.0, 3e-7)
    r2 = rng.standard_normal(m) ** 2 * (var + extra)
    return r2, var, m - int(rng.integers(1, 15))


@pytest.mark.parametrize("seed", range(40))
def test_floor_solves_the_reduced_chi2_equation_as_brentq_does(seed):
    r2, var, dof = _case(seed)

    def excess(f2: float) -> float:
        return float(np.sum(r2 / np.maximum(var + f2, TINY)) - dof)

    f2 = quasi_static_floor(r2, var, dof, TINY)
    if excess(0.0) <= 0:
        assert f2 == 0.0
        return
    ref = brentq(excess, 0.0, max(r2.max(), 1e-12) * 10, xtol=1e-18, rtol=1e-10)
    assert f2 == pytest.approx(ref, rel=1e-8)
    assert abs(excess(f2)) <= 1e-6 * dof  # chi² / dof = 1 at the floor


def test_floor_is_the_bracket_top_when_no_floor_brings_chi2_down():
    r2 = np.ones(30)  # sum r2 / (v + 10) = 3 > dof = 2 even at the bracket's top, 10 max(r2)
    var = np.full(30, 1e-12)
    assert quasi_static_floor(r2, var, 2, TINY) == 10.0


def test_floor_is_zero_when_chi2_is_already_below_one():
    rng = np.random.default_rng(3)
    var = np.full(500, 1e-8)
    r2 = 0.5 * rng.standard_normal(500) ** 2 * var
    assert quasi_static_floor(r2, var, 490, TINY) == 0.0
