"""The offline fit does work once that several of its steps need (core/estimators/order_fit.py fit_order
and _auto_extended, core/estimators/order.py compare_extended): each shortcut must give exactly (bit for
bit) what the separate computation gives, so no decision or printed figure depends on it.

Windows: core.crlb.windows_on_ellipsoid (as tests/core/test_order.py) and core.estimators.remount's
session_windows with a temperature ramp (as tests/core/test_extended_fit.py). No statistics: the checks
are equalities of deterministic computations.
"""
from __future__ import annotations

import numpy as np
import pytest

from gravcal.core.calibration import Calibration
from gravcal.core.crlb import cap_directions, windows_on_ellipsoid
from gravcal.core.estimators import order
from gravcal.core.estimators.extended import model_name
from gravcal.core.estimators.lotters import LottersBatch
from gravcal.core.estimators.remount import session_windows
from gravcal.core.model.defaults import default_model
from gravcal.core.estimators.order_fit import AUTO_EXTENDED_TERMS, fit_order

D = np.diag([0.125, 0.131, 0.118])
O = np.array([0.502, 0.493, 0.508])
MISALIGNED = D @ np.array([[1, 0.004, 0.0], [0.0, 1, 0.0], [0.018, -0.015, 1]])
NOMINAL = Calibration("nominal", [0.5, 0.5, 0.5], np.eye(3) * 0.125)


@pytest.fixture(scope="module")
def ramp_windows():
    """100 windows spread over a 1.5 h session with a 22 -> 32 °C ramp, and the 6-parameter fit."""
    ws, _ = session_windows("loetters", seed=0, duration=5400.0, model=default_model(0, temperature_offset=True),
                            temp_c=lambda t: 22.0 + 10.0 * t / 5400.0)
    ws = ws.subset(np.unique(np.linspace(0, len(ws) - 1, 100).astype(int)))
    return ws, LottersBatch("6").fit(ws)


def terms_testable_on(ws) -> list[str]:
    terms = [t for t in AUTO_EXTENDED_TERMS if order.term_testability(ws, t)[0]]
    assert len(terms) >= 2, terms  # temperature and time terms on these windows
    return terms


def test_compare_extended_with_shared_base_fits_equals_separate_comparisons(ramp_windows, monkeypatch):
    ws, at = ramp_windows
    terms = terms_testable_on(ws)
    # one- and two-term candidates: with 100 windows they get 5 and 4 folds, so the base's folds differ too
    cands = [model_name("6", (t,)) for t in terms] + [model_name("6", tuple(terms[:2]))]
    separate = [order.compare_extended(ws, "6", c, at) for c in cands]
    calls = []
    real = order.fit_extended
    monkeypatch.setattr(order, "fit_extended", lambda *a, **k: calls.append(a[0].model) or real(*a, **k))
    shared: dict = {}
    together = [order.compare_extended(ws, "6", c, at, shared=shared) for c in cands]
    assert together == separate
    ks = [min(5, len(ws) // (2 * e["n_params"])) for e in (s[c] for s, c in zip(separate, cands))]
    assert sorted(set(ks)) == [4, 5]
    # the base fitted (with its folds) once per fold count, each candidate once
    assert calls.count("6") == sum(1 + k for k in set(ks))
    assert len(calls) - calls.count("6") == sum(1 + k for k in ks)


def test_fold_windows_are_made_once_per_comparison(ramp_windows, monkeypatch):
    """compare_orders and a round of compare_extended take each fold's training and held-out windows once
    (order.fold_splits) for every model they compare, with the scores of subsets made per model."""
    ws, at = ramp_windows
    terms = terms_testable_on(ws)
    cands = [model_name("6", (t,)) for t in terms]
    made = []
    real = type(ws).subset
    monkeypatch.setattr(type(ws), "subset", lambda self, idx: made.append(len(idx)) or real(self, idx))
    shared: dict = {}
    together = [order.compare_extended(ws, "6", c, at, shared=shared) for c in cands]
    assert len(made) == 2 * 5  # 5 folds (100 windows, 9 parameters), a training and a held-out set each
    made.clear()
    scores = order.compare_orders(ws, ("6", "9"), at)
    assert len(made) == 2 * 5
    # the same scores from subsets made afresh for every model and fold
    monkeypatch.setattr(order, "fold_splits", lambda w, o, k: [(i, real(w, order.complement(i, len(w))), real(w, i))
                                                                for i in np.array_split(o, k)])
    fresh_splits = order.fold_splits
    calls = []
    monkeypatch.setattr(order, "fold_splits", lambda *a: calls.append(1) or fresh_splits(*a))
    assert [order.compare_extended(ws, "6", c, at) for c in cands] == together
    fresh = order.compare_orders(ws, ("6", "9"), at)
    fresh.pop("_fits"), scores.pop("_fits")
    assert fresh == scores and len(calls) == len(cands) + 1


def test_complement_is_setdiff1d_of_a_permutation():
    rng = np.random.default_rng(3)
    for m in (1, 2, 7, 100, 1001):
        order_ = rng.permutation(m)
        for idx in np.array_split(order_, min(5, m)):
            got = order.complement(idx, m)
            want = np.setdiff1d(order_, idx)
            assert got.dtype == want.dtype and np.array_equal(got, want)


@pytest.mark.parametrize("K, chosen", [(D, "6"), (MISALIGNED, "9")])
def test_auto_keeps_the_comparison_fit_equal_to_a_fresh_fit(K, chosen):
    rng = np.random.default_rng(2)
    ws = windows_on_ellipsoid(Calibration("truth", O, K), cap_directions((0, 0, 1), 180, 200, rng), noise_g=0.005,
                              n=300, rng=rng)
    fitted = fit_order(ws, "auto", NOMINAL, None, None, 5)
    assert fitted.model == chosen
    fresh = LottersBatch(chosen).fit(ws, order.reference_start(chosen, NOMINAL, None))
    got, want = fitted.calibration.to_dict(), fresh.to_dict()
    for key in ("model", "offset", "sensitivity", "covariance", "std", "converged", "observable", "message"):
        assert got[key] == want[key], key
    assert {k: v for k, v in got["metadata"].items() if not k.startswith("frame")} == want["metadata"]


def fold_cases(ramp_windows):
    ws, _ = ramp_windows
    rng = np.random.default_rng(4)
    rich = windows_on_ellipsoid(Calibration("truth", O, MISALIGNED), cap_directions((0, 0, 1), 180, 60, rng),
                                noise_g=0.005, n=300, rng=rng)
    ext = model_name("6", (terms_testable_on(ws)[0],))
    return [(rich, LottersBatch("offsets"), NOMINAL), (rich, LottersBatch("6"), NOMINAL),
            (rich, LottersBatch("9", sigma_floor_g=0.002), NOMINAL), (rich, LottersBatch("6", outlier_gate_sigma=3.0), None),
            (rich, LottersBatch("6", max_iter=1), NOMINAL), (ws, LottersBatch(ext), None)]  # the 5th: not converged


def test_fit_fold_gives_the_parameters_of_fit(ramp_windows):
    for ws, est, start in fold_cases(ramp_windows):
        for train in (np.arange(len(ws)) % 5 != k for k in range(2)):
            full = est.fit(ws.subset(np.flatnonzero(train)), start)
            fold = est.fit_fold(ws.subset(np.flatnonzero(train)), start)
            assert np.array_equal(fold.offset, full.offset) and np.array_equal(fold.sensitivity, full.sensitivity)
            assert fold.converged == full.converged and not fold.observable and "not judged" in fold.message
            for key in ("params", "iterations", "chi2", "sigma_floor_g", "outlier_windows"):
                assert fold.metadata.get(key) == full.metadata.get(key), (est.model, key)
            assert (fold.metadata.get("extended") is None) == (full.metadata.get("extended") is None)


def test_heldout_error_scores_fold_fits_as_the_full_fit_would(ramp_windows):
    from gravcal.core.heldout import fold_indices, heldout_error, norm_error_mg

    for ws, est, start in fold_cases(ramp_windows):
        res = heldout_error(ws, est.model, start=start, estimator=est)
        errors = []
        for test in fold_indices(ws.t, "contiguous", 5):
            train = np.setdiff1d(np.arange(len(ws)), test)
            errors.append(norm_error_mg(est.fit(ws.subset(train), start), ws.subset(test)))
        assert res.fold_rms_mg == [float(np.sqrt(np.mean(e ** 2))) for e in errors]
        assert res.heldout_rms_mg == float(np.sqrt(np.mean(np.concatenate(errors) ** 2)))
