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
from gravcal.core.heldout import HeldoutResult, fold_indices, norm_error_mg, rms_mg
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
    all_idx = np.arange(len(ws))
    for test in fold_indices(ws.t, "contiguous", folds):
        train = ws.subset(np.setdiff1d(all_idx, test, assume_unique=True))
        try:
            out.append((test, estimator.fit_fold(train, fold_bootstrap(train))))
        except (ValueError, np.linalg.LinAlgError) as exc:
            out.append((test, str(exc)))
    return out


def heldout_own_start(ws: WindowSet, estimator: LottersBatch, folds: int, full_fit: Calibration) -> HeldoutResult:
    """The held-out error of a fit whose start (and held sensitivities) the bootstrap drew from these same
    windows: each fold bootstraps its own start from its training windows (``fold_fits_own_start``), as the
    procedure the user gets did from all of them."""
    per_window = np.full(len(ws), np.nan)
    fold_rms, sizes, notes = [], [], []
    for k, (test, cal) in enumerate(fold_fits_own_start(ws, estimator, folds)):
        if isinstance(cal, str):
            notes.append(f"fold {k}: not fitted ({cal})")
            continue
        if not cal.converged:
            notes.append(f"fold {k}: fit did not converge")
        e = norm_error_mg(cal, ws.subset(test))
        per_window[test] = e
        fold_rms.append(float(np.sqrt(np.mean(e ** 2))))
        sizes.append(int(test.size))
    done = per_window[np.isfinite(per_window)]
    held = float(np.sqrt(np.mean(done ** 2))) if done.size else float("nan")
    notes.append("held-out of the offsets-only fit: each fold's held sensitivities bootstrapped from its training "
                 "windows only")
    return HeldoutResult(held, rms_mg(full_fit, ws), "contiguous", folds, fold_rms, sizes, notes,
                         window_errors_mg=per_window)
