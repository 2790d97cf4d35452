"""core/quantiles.py: np.median's and np.percentile's values, bit for bit, without loading numpy.ma."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from gravcal.core.quantiles import median, percentile


def _cases(seed: int):
    rng = np.random.default_rng(seed)
    for n in (1, 2, 3, 4, 5, 10, 11, 64, 65, 1000, 1001):
        x = rng.normal(size=n) * 10 ** rng.uniform(-8, 8)
        yield x
        yield np.round(x, 1)  # ties
        if n > 2:
            y = x.copy()
            y[rng.integers(n)] = np.inf
            yield y
            y = x.copy()
            y[rng.integers(n)] = -np.inf
            y[rng.integers(n)] = np.inf
            yield y
            y = x.copy()
            y[rng.integers(n)] = np.nan
            yield y
            yield np.where(x > 0, 0.0, -0.0)


def _same(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


@pytest.mark.parametrize("seed", range(4))
def test_median_is_numpys(seed):
    for x in _cases(seed):
        assert _same(median(x), np.median(x)), x
        m = np.column_stack([x, x[::-1], np.sort(x)])
        assert _same(median(m, axis=0), np.median(m, axis=0))
        assert _same(median(m.T, axis=1), np.median(m.T, axis=1))
        assert _same(median(m.T, axis=-1), np.median(m.T, axis=-1))
    assert _same(median([3, 1, 2, 4]), np.median([3, 1, 2, 4]))  # integers: numpy's float mean


@pytest.mark.parametrize("seed", range(4))
def test_percentile_is_numpys(seed):
    qs = (0, 0.5, 1, 5, 12.5, 25, 33.3, 50, 66.7, 95, 99.9, 100)
    for x in _cases(seed):
        for q in qs:
            assert _same(percentile(x, q), np.percentile(x, q)), (x, q)
    for q in (5, 50.0):  # what it hands to numpy
        assert _same(percentile(np.arange(10, dtype=np.float32), q), np.percentile(np.arange(10, dtype=np.float32), q))


def test_empty_input_is_numpys_nan():
    with pytest.warns(RuntimeWarning):
        assert np.isnan(median(np.zeros(0)))


def test_neither_loads_numpy_ma():
    code = ("import sys, numpy as np\n"
            "from gravcal.core.quantiles import median, percentile\n"
            "x = np.random.default_rng(0).normal(size=1001)\n"
            "median(x); median(x.reshape(7, 143), axis=0); percentile(x, 5)\n"
            "print('numpy.ma' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60).stdout
    assert out.strip() == "False"
