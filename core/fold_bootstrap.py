"""Held-out folds of a fit whose start the bootstrap drew from the same windows.

An offsets-only fit holds its sensitivities at the start. When that start is the bootstrap's ellipsoid fit
of the recording's still windows, the held sensitivities were fitted to every window, the held-out fold's
included: folds started from it score windows that shaped what the fold holds. Here each fold bootstraps
its own start from its training windows, as the delivered procedure did from all of them.
"""
from __future__ import annotations

import numpy as np

from gravcal.core.calibration import Calibration
from gravcal.core.estimators.lotters import LottersBatch
from gravcal.core.estimators.start import ellipsoid_fit
from gravcal.core.heldout import HeldoutResult, fold_indices, score_folds, train_test_splits
from gravcal.core.windows import WindowSet


def fold_bootstrap(ws: WindowSet) -> Calibration:
    """The bootstrap's start from these windows alone: their ellipsoid fit, or (too little orientation
    coverage for per-axis sensitivities) the isotropic scale of their median norm, as start.bootstrap falls
    back to."""
    try:
        return ellipsoid_fit(ws)
    except ValueError:
        scale = float(np.median(np.linalg.norm(ws.mean, axis=1)))
        return Calibration("start", np.zeros(3), scale * np.eye(3), n_windows=len(ws), converged=False,
                           observable=False, message="isotropic scale of the fold's windows")


def fold_fits_own_start(ws: WindowSet, estimator: LottersBatch, folds: int) -> list[tuple[np.ndarray, Calibration | str]]:
    """(held-out indices, the fit of the other windows or why it failed) of every contiguous fold, each fit
    started from, and holding what it does not fit at, ``fold_bootstrap`` of its own training windows: the
    held-out windows shape nothing the fold's fit uses."""
    out: list[tuple[np.ndarray, Calibration | str]] = []
    for test, train_idx in train_test_splits(len(ws), fold_indices(ws.t, "contiguous", folds)):
        train = ws.subset(train_idx)
        try:
            out.append((test, estimator.fit_fold(train, fold_bootstrap(train))))
        except (ValueError, np.linalg.LinAlgError) as exc:
            out.append((test, str(exc)))
    return out


def heldout_own_start(ws: WindowSet, estimator: LottersBatch, folds: int, full_fit: Calibration) -> HeldoutResult:
    """The held-out error of a fit whose start (and held sensitivities) the bootstrap drew from these same
    windows: each fold bootstraps its own start from its training windows (``fold_fits_own_start``), as the
    procedure the user gets did from all of them."""
    result = score_folds(ws, fold_fits_own_start(ws, estimator, folds), "contiguous", folds, full_fit)
    result.notes.append("held-out of the offsets-only fit: each fold's held sensitivities bootstrapped from its "
                        "training windows only")
    return result
