"""Quasi-static windows: what the detectors emit and the estimators consume.

A window is summarised by sufficient statistics only (count, mean, covariance of the
samples, and the means of auxiliary channels such as temperature), so that a week of data
becomes a few thousand rows and estimators never touch samples again.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .calibration import Calibration
from .model.spec import AUX_COLUMNS

MAX_WINDOW_STD_G = 0.05  # per-axis std inside a window above which it is not quasi-static [g] (bias < 1.3 mg)


@dataclass(frozen=True)
class Window:
    start: int  # index of the first sample (global, counted from the start of the stream)
    end: int  # index one past the last sample
    t_start: float  # time of the first sample [s]
    t_end: float  # time of the last sample [s]
    mean: np.ndarray  # (3,) mean of the samples, in the units the detector was fed
    cov: np.ndarray  # (3, 3) sample covariance (ddof=1) of the samples
    aux_mean: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (k,) means of auxiliary channels (e.g. temperature)

    @property
    def n(self) -> int:
        return self.end - self.start

    @property
    def t_mid(self) -> float:
        return 0.5 * (self.t_start + self.t_end)


@dataclass
class WindowSet:
    """Windows as arrays (M rows), the form estimators take."""

    mean: np.ndarray  # (M, 3)
    cov: np.ndarray  # (M, 3, 3) sample covariance
    n: np.ndarray  # (M,)
    t: np.ndarray  # (M,) mid time [s]
    aux: np.ndarray  # (M, k)
    start: np.ndarray  # (M,)
    end: np.ndarray  # (M,)

    def __len__(self) -> int:
        return int(self.mean.shape[0])

    @property
    def cov_of_mean(self) -> np.ndarray:
        """Covariance of each window mean (white-noise assumption): cov / n."""
        return self.cov / self.n[:, None, None]

    def subset(self, idx: np.ndarray) -> "WindowSet":
        idx = np.asarray(idx)
        return WindowSet(self.mean[idx], self.cov[idx], self.n[idx], self.t[idx], self.aux[idx], self.start[idx], self.end[idx])

    def covariate(self, name: str) -> np.ndarray | None:
        """The windows' mean of an aux channel by name (``AUX_COLUMNS``: temp [°C], vsupply [V]); time [s]
        is ``t``. None when the windows carry no such column."""
        if name == "time":
            return self.t
        col = AUX_COLUMNS.index(name)
        if self.aux.ndim != 2 or self.aux.shape[1] <= col:
            return None
        return self.aux[:, col]

    @classmethod
    def from_windows(cls, windows: list[Window]) -> "WindowSet":
        m = len(windows)
        k = windows[0].aux_mean.shape[0] if m else 0
        return cls(
            mean=np.array([w.mean for w in windows], dtype=float).reshape(m, 3),
            cov=np.array([w.cov for w in windows], dtype=float).reshape(m, 3, 3),
            n=np.array([w.n for w in windows], dtype=float),
            t=np.array([w.t_mid for w in windows], dtype=float),
            aux=np.array([w.aux_mean for w in windows], dtype=float).reshape(m, k),
            start=np.array([w.start for w in windows], dtype=np.int64),
            end=np.array([w.end for w in windows], dtype=np.int64),
        )

    @classmethod
    def from_points(cls, mean: np.ndarray, var: float | np.ndarray, n: int = 1) -> "WindowSet":
        """Windows from bare mean vectors (M, 3) with isotropic per-sample variance ``var``
        (the paper's simulation: points on the ellipsoid with C_mu diagonal)."""
        mean = np.asarray(mean, dtype=float).reshape(-1, 3)
        m = mean.shape[0]
        v = np.broadcast_to(np.asarray(var, dtype=float), (m,))
        cov = v[:, None, None] * np.eye(3)[None] * n
        return cls(mean, cov, np.full(m, float(n)), np.arange(m, dtype=float), np.zeros((m, 0)),
                   np.arange(m, dtype=np.int64), np.arange(m, dtype=np.int64) + 1)


def validate_windows(ws: WindowSet, n_params: int | None = None) -> None:
    """Raise ValueError naming the problem if ``ws`` cannot be used for a fit."""
    if not isinstance(ws, WindowSet):
        raise ValueError(f"expected a WindowSet, got {type(ws).__name__}")
    m = len(ws)
    if m == 0:
        raise ValueError("no quasi-static windows: nothing to calibrate from (is the recording all motion, or too short?)")
    finite = (np.isfinite(ws.mean).all() and np.isfinite(ws.cov).all() and np.isfinite(ws.t).all()
              and np.isfinite(ws.n).all() and (ws.n > 0).all())
    if not finite:  # per-row masks only to name the culprits (the order rules call this on every check)
        _name_nonfinite(ws, m)
    if n_params is not None:
        require_windows(m, n_params)


def _name_nonfinite(ws: WindowSet, m: int) -> None:
    """Raise ValueError naming the first kind of non-finite (or non-positive count) window and which ones."""
    bad = ~np.all(np.isfinite(ws.mean), axis=1)
    if bad.any():
        idx = np.flatnonzero(bad)
        raise ValueError(f"{idx.size} window mean(s) are NaN/inf (windows {idx[:5].tolist()}{'...' if idx.size > 5 else ''})")
    badc = ~np.all(np.isfinite(ws.cov.reshape(m, 9)), axis=1)
    if badc.any():
        idx = np.flatnonzero(badc)
        raise ValueError(f"{idx.size} window covariance(s) are NaN/inf (windows {idx[:5].tolist()})")
    badn = ~(ws.n > 0) | ~np.isfinite(ws.n)
    if badn.any():
        raise ValueError(f"{int(badn.sum())} window sample count(s) are not positive finite numbers "
                         f"(windows {np.flatnonzero(badn)[:5].tolist()})")
    badt = ~np.isfinite(ws.t)
    if badt.any():
        raise ValueError(f"{int(badt.sum())} window time(s) are NaN/inf (windows {np.flatnonzero(badt)[:5].tolist()})")


def require_windows(m: int, n_params: int) -> None:
    """Raise ValueError unless ``m`` windows can determine ``n_params`` parameters."""
    if m < n_params:
        raise ValueError(
            f"{m} quasi-static window(s) for {n_params} parameters: need at least {n_params} "
            f"(more, spread over orientations, for a useful estimate)"
        )


def window_std_g(ws: WindowSet, cal: Calibration) -> np.ndarray:
    """Largest per-axis std [g] of the samples inside each window, under ``cal``: above MAX_WINDOW_STD_G a
    window averages postures (a slow turn at constant |a|), its mean lies inside the ellipsoid."""
    Kinv = np.linalg.inv(cal.sensitivity)
    cov_g = np.einsum("ij,mjk,lk->mil", Kinv, ws.cov, Kinv)
    return np.sqrt(np.clip(np.diagonal(cov_g, axis1=1, axis2=2), 0, None)).max(axis=1)
