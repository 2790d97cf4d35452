"""Held-out error of a calibration: quasi-static windows not used for the fit.

The error measure is the one the method itself rests on (Lötters eq. 4): at a quasi-static
window the calibrated |a| must be 1 g, so RMS(|a| - 1 g) [mg] over windows the fit did not see
tells how well the calibration generalises. In-sample RMS is always smaller (the fit adapted
to those windows); report both.

Folds are CONSECUTIVE in time by default: neighbouring windows of a recording are correlated
(same posture, same temperature), so random folds would leak and flatter the result.
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gravcal.core.calibration import Calibration
from gravcal.core.estimators.extended import apply_windows
from gravcal.core.estimators.lotters import LottersBatch
from gravcal.core.windows import WindowSet

SCHEMES = ("contiguous", "halves")


def norm_error_mg(cal: Calibration, ws: WindowSet) -> np.ndarray:
    """|a| - 1 g [mg] of each window mean under ``cal``; an extended calibration (temperature, drift
    terms) is applied at each window's temperature (``ws.aux``) and mid time."""
    a = apply_windows(cal, ws)
    return (np.linalg.norm(a, axis=1) - 1.0) * 1e3


def rms_mg(cal: Calibration, ws: WindowSet) -> float:
    """RMS of |a| - 1 g [mg] over the windows."""
    e = norm_error_mg(cal, ws)
    return float(np.sqrt(np.mean(e**2))) if e.size else float("nan")


def fold_indices(t: np.ndarray, scheme: str = "contiguous", folds: int = 5) -> list[np.ndarray]:
    """Held-out index sets (into the original order) for each fold.

    contiguous: ``folds`` blocks of consecutive windows in time; halves: first / second half in
    time. Interleaved folds (every other window) are not offered: neighbours in time share posture and
    temperature, so they leak.
    """
    t = np.asarray(t, dtype=float)
    order = np.argsort(t, kind="stable")
    m = order.size
    if scheme == "contiguous":
        if folds < 2:
            raise ValueError(f"need at least 2 folds, got {folds}")
        if m < folds:
            raise ValueError(f"{m} windows cannot be split into {folds} folds")
        return [np.sort(b) for b in np.array_split(order, folds)]
    if scheme == "halves":
        if m < 2:
            raise ValueError(f"{m} windows cannot be split into halves")
        return [np.sort(b) for b in np.array_split(order, 2)]
    raise ValueError(f"unknown held-out scheme {scheme!r}; known: {', '.join(SCHEMES)}")


@dataclass
class HeldoutResult:
    heldout_rms_mg: float  # RMS |a| - 1 g over all held-out windows (pooled over folds) [mg]
    insample_rms_mg: float  # RMS |a| - 1 g of the full fit over all windows [mg]
    scheme: str
    folds: int
    fold_rms_mg: list[float] = field(default_factory=list)  # per fold [mg]
    fold_sizes: list[int] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    window_errors_mg: np.ndarray | None = None  # |a| - 1 g of each window when held out [mg] (NaN: fold not fitted)

    def to_dict(self) -> dict[str, Any]:
        return {"heldout_rms_mg": self.heldout_rms_mg, "insample_rms_mg": self.insample_rms_mg, "scheme": self.scheme,
                "folds": self.folds, "fold_rms_mg": list(self.fold_rms_mg), "fold_sizes": list(self.fold_sizes),
                "notes": list(self.notes)}


def heldout_error(
    ws: WindowSet,
    model: Any = "6",
    *,
    scheme: str = "contiguous",
    folds: int = 5,
    start: Calibration | None = None,
    full_fit: Calibration | None = None,
    estimator: LottersBatch | None = None,
) -> HeldoutResult:
    """Fit on all folds but one, evaluate RMS(|a| - 1 g) on the held-out one, for every fold.

    ``start`` is the starting point of every fold fit (None: each fold derives its own ellipsoid
    start from its training windows, so nothing from the held-out fold leaks). ``full_fit`` (the
    calibration from all windows) gives the in-sample RMS; fitted here if not given.
    A fold whose training windows cannot be fitted (too few windows) is skipped and noted.
    """
    est = estimator if estimator is not None else LottersBatch(model)
    if full_fit is None:
        full_fit = est.fit(ws, start)
    held = fold_indices(ws.t, scheme, folds)

    def fits() -> Iterable[tuple[np.ndarray, Calibration | str]]:
        for test, train in train_test_splits(len(ws), held):
            try:
                yield test, est.fit_fold(ws.subset(train), start)
            except ValueError as exc:
                yield test, str(exc)

    return score_folds(ws, fits(), scheme, len(held), full_fit)


def train_test_splits(m: int, held: list[np.ndarray]) -> Iterable[tuple[np.ndarray, np.ndarray]]:
    """(held-out, training) indices of each fold: the training windows are all the others."""
    all_idx = np.arange(m)
    for test in held:
        yield test, np.setdiff1d(all_idx, test, assume_unique=True)


def score_folds(ws: WindowSet, fold_fits: Iterable[tuple[np.ndarray, Calibration | str]], scheme: str, folds: int,
                full_fit: Calibration) -> HeldoutResult:
    """Score each fold's fit on its held-out windows: ``fold_fits`` gives (held-out indices, the fit of the
    other windows, or why it failed) per fold. The held-out RMS pools every fitted fold's windows; a fold
    not fitted or not converged is noted; ``full_fit`` gives the in-sample RMS."""
    errors: list[np.ndarray] = []
    fold_rms: list[float] = []
    sizes: list[int] = []
    notes: list[str] = []
    per_window = np.full(len(ws), np.nan)
    for k, (test, cal) in enumerate(fold_fits):
        if isinstance(cal, str):
            notes.append(f"fold {k}: not fitted ({cal})")
            continue
        if not cal.converged:
            notes.append(f"fold {k}: fit did not converge")
        e = norm_error_mg(cal, ws.subset(test))
        per_window[test] = e
        errors.append(e)
        fold_rms.append(float(np.sqrt(np.mean(e**2))))
        sizes.append(int(test.size))
    pooled = np.concatenate(errors) if errors else np.zeros(0)
    heldout = float(np.sqrt(np.mean(pooled**2))) if pooled.size else float("nan")
    if not errors:
        notes.append("no fold could be fitted: held-out error unavailable")
    return HeldoutResult(heldout, rms_mg(full_fit, ws), scheme, folds, fold_rms, sizes, notes, per_window)
