"""Held-out error: contiguous folds, schemes, held-out > in-sample."""
from __future__ import annotations

import numpy as np
import pytest

from gravcal.core.calibration import Calibration
from gravcal.core.estimators.lotters import LottersBatch
from gravcal.core.fold_bootstrap import fold_fits_own_start, heldout_own_start
from gravcal.core.heldout import fold_indices, heldout_error, norm_error_mg, rms_mg, score_folds
from gravcal.core.windows import WindowSet

K = np.diag([0.125, 0.118, 0.131])
O = np.array([0.502, 0.487, 0.515])


def windows(rng, m, floor_g=0.003):
    """Window means on the ellipsoid with an unmodelled |a| scatter of floor_g (what held-out sees)."""
    u = rng.normal(size=(m, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    a = u * (1 + floor_g * rng.standard_normal(m))[:, None]
    cov = np.repeat((1e-4 * np.eye(3))[None], m, 0)
    t = rng.permutation(m) * 7.0  # times not in row order: folds must follow time, not rows
    return WindowSet(a @ K.T + O, cov, np.full(m, 200.0), t, np.zeros((m, 0)), np.arange(m), np.arange(m) + 1)


def test_contiguous_folds_partition_and_are_consecutive_in_time():
    rng = np.random.default_rng(0)
    t = rng.permutation(53) * 3.0
    folds = fold_indices(t, "contiguous", 5)
    assert len(folds) == 5
    allidx = np.concatenate(folds)
    assert sorted(allidx.tolist()) == list(range(53))
    rank = np.argsort(np.argsort(t))  # position of each window in time
    for f in folds:
        r = np.sort(rank[f])
        assert np.all(np.diff(r) == 1)  # consecutive in time
    assert [f.size for f in folds] == [11, 11, 11, 10, 10]


def test_halves_and_no_interleaved_scheme():
    t = np.arange(10.0)[::-1]
    h = fold_indices(t, "halves")
    assert sorted(h[0].tolist()) == [5, 6, 7, 8, 9]  # earliest times are the last rows
    for leaky in ("oddeven", "random"):
        with pytest.raises(ValueError, match="unknown held-out scheme"):
            fold_indices(t, leaky)
    with pytest.raises(ValueError, match="cannot be split"):
        fold_indices(np.arange(3.0), "contiguous", 5)


def test_heldout_rms_exceeds_insample_on_average():
    """Over 20 seeds the held-out RMS must exceed the in-sample RMS on average (the fit adapts to
    its own windows: in-sample is biased low by ~P/M, here 6/40 of the variance)."""
    ratios = []
    for seed in range(20):
        rng = np.random.default_rng(seed)
        ws = windows(rng, 40)
        res = heldout_error(ws, "6", scheme="contiguous", folds=5)
        assert len(res.fold_rms_mg) == 5 and sum(res.fold_sizes) == 40
        ratios.append(res.heldout_rms_mg / res.insample_rms_mg)
        # both are near the planted 3 mg scatter
        assert 1.0 < res.insample_rms_mg < 5.0 and 1.0 < res.heldout_rms_mg < 8.0
    assert np.mean(ratios) > 1.05, np.mean(ratios)
    assert np.mean(np.array(ratios) > 1) > 0.75


def test_rms_mg_of_truth_is_the_planted_scatter():
    rng = np.random.default_rng(1)
    ws = windows(rng, 2000, floor_g=0.004)
    truth = Calibration("truth", O, K)
    assert abs(rms_mg(truth, ws) - 4.0) < 0.3  # 4 mg planted; 2000 windows -> 1.6 % relative std


def test_folds_too_small_are_skipped_with_a_note():
    rng = np.random.default_rng(2)
    ws = windows(rng, 10)
    res = heldout_error(ws, "6", folds=2, estimator=LottersBatch("6"))  # 5 training windows < 6 parameters
    assert np.isnan(res.heldout_rms_mg) and res.fold_rms_mg == []
    assert sum("not fitted" in n for n in res.notes) == 2 and "unavailable" in res.notes[-1]
    res3 = heldout_error(windows(rng, 12), "offsets", folds=2, start=Calibration("s", O, K))
    assert np.isfinite(res3.heldout_rms_mg) and len(res3.fold_rms_mg) == 2


def test_each_window_is_scored_by_its_own_folds_fit_in_both_procedures():
    """heldout_error and heldout_own_start (each fold bootstraps its own start) score alike: a window's
    held-out error is |a| - 1 g under the fit of the other folds, the pooled RMS is over every scored
    window, and a fold that could not be fitted leaves its windows unscored and says why."""
    rng = np.random.default_rng(3)
    ws = windows(rng, 30)
    est = LottersBatch("offsets")
    full = est.fit(ws, Calibration("s", O, K))
    fits = fold_fits_own_start(ws, est, 3)
    own = heldout_own_start(ws, est, 3, full_fit=full)
    for test, cal in fits:
        np.testing.assert_array_equal(own.window_errors_mg[test], norm_error_mg(cal, ws.subset(test)))
    assert own.heldout_rms_mg == pytest.approx(np.sqrt(np.mean(own.window_errors_mg ** 2)), rel=1e-12)
    assert own.insample_rms_mg == rms_mg(full, ws) and own.fold_sizes == [10, 10, 10]
    start = Calibration("s", O, K)
    fixed = heldout_error(ws, "offsets", folds=3, start=start, full_fit=full, estimator=est)
    for test in fold_indices(ws.t, "contiguous", 3):
        train = np.setdiff1d(np.arange(30), test)
        cal = est.fit_fold(ws.subset(train), start)
        np.testing.assert_array_equal(fixed.window_errors_mg[test], norm_error_mg(cal, ws.subset(test)))
    failed = score_folds(ws, [fits[0], (fits[1][0], "too few windows"), fits[2]], "contiguous", 3, full)
    assert np.isnan(failed.window_errors_mg[fits[1][0]]).all()
    assert "fold 1: not fitted (too few windows)" in failed.notes
    scored = np.concatenate([own.window_errors_mg[fits[0][0]], own.window_errors_mg[fits[2][0]]])
    assert failed.heldout_rms_mg == pytest.approx(np.sqrt(np.mean(scored ** 2)), rel=1e-12)
