"""Streaming quasi-static detectors: raw triad samples in, quasi-static Windows out.

Two detectors share one windowing engine (:class:`_Windower`):

- :class:`QuasiStaticDetector` — Lötters et al. 1998, section 2: the modulus of the triad
  (eq. 1) goes through a 0.5 Hz high-pass filter, a rectifier and a 0.5 Hz low-pass filter
  (eq. 2); a sample is quasi-static when that detection signal is below a threshold.
- :class:`MovingVarianceDetector` — per-axis moving variance over a trailing window; a
  sample is quasi-static when every axis's moving standard deviation is below a threshold.

Both take raw samples (N, 3) in any units. The detection signal is computed on
``to_g(raw)`` (a :class:`~gravcal.core.calibration.Calibration`, a callable raw -> g, or
identity when None), so thresholds are in g — or in raw units when ``to_g`` is None.
Window means and covariances are always of the RAW samples: the estimators work in raw units.

Windowing rules (identical for both detectors):

- a sample is *still* when it is finite (raw, time and aux), its detection signal is below
  the threshold, the filters have settled since the first finite sample, and it does not
  follow a time gap (a jump larger than 1.5/fs, or time not increasing);
- a sample is *in a window* when every sample within ``guard_s`` of it is still (erosion of
  the still mask; the detection signal lags the motion, so the edges of a still period are
  trimmed). The stream's end counts as not still, so flush() trims the last guard too;
- a run of in-window samples is cut into consecutive windows of ``max_duration_s``
  counted from the run's first sample (so a 3-hour pose yields many windows); windows
  shorter than ``min_duration_s`` (including a short remainder) are dropped.

Streaming is exact: every decision is a function of the sample stream alone, never of how
it was split into blocks. Filter states (sosfilt ``zi``) and running sums (np.cumsum
with the carried sum prepended) evaluate the same floating-point operations in the same
order for any split, so window boundaries are bit-identical; window means/covariances are
accumulated per block with np.add.reduceat and agree to rounding (tests: means 1e-12,
covariances 1e-8 relative).
A sample is decided ``guard`` samples after it arrives (the erosion looks ahead).
"""
from __future__ import annotations

import numpy as np

from ..windows import WindowSet
from .quasistatic import QuasiStaticDetector
from .variance import MovingVarianceDetector
from .windowing import _DETECT_BLOCK, ToG

__all__ = ["DETECTORS", "MovingVarianceDetector", "QuasiStaticDetector", "ToG", "detect", "estimate_fs"]


DETECTORS = {"lotters": QuasiStaticDetector, "variance": MovingVarianceDetector}


def estimate_fs(t: np.ndarray) -> float:
    """Sample rate [Hz] from the median time step of finite, increasing timestamps."""
    t = np.asarray(t, dtype=float)
    dt = np.diff(t[np.isfinite(t)])
    dt = dt[dt > 0]
    if dt.shape[0] == 0:
        raise ValueError("cannot estimate the sample rate: fewer than two increasing finite timestamps (pass fs)")
    return float(1.0 / np.median(dt))


def detect(t, raw, *, method: str = "lotters", fs: float | None = None, to_g: ToG = None, aux=None, **kw) -> WindowSet:
    """All quasi-static windows of a recording, as a WindowSet (blocks of 65536 samples + flush).

    method "lotters" (QuasiStaticDetector) or "variance" (MovingVarianceDetector); fs [Hz]
    is estimated from t when None; ``kw`` go to the detector (threshold_g, guard_s, ...).
    """
    if method not in DETECTORS:
        raise ValueError(f"unknown detector method {method!r}; choose one of {sorted(DETECTORS)}")
    fs = estimate_fs(t) if fs is None else fs
    det = DETECTORS[method](fs, to_g=to_g, **kw)
    t, raw = np.asarray(t), np.asarray(raw)
    aux = None if aux is None else np.asarray(aux)
    n = t.shape[0] if t.ndim == 1 else -1
    if raw.ndim != 2 or raw.shape[0] != n or (aux is not None and aux.shape[0] != n):
        windows = det.update(t, raw, aux)  # raises, naming the problem
    else:
        windows = []
        for i in range(0, n, _DETECT_BLOCK):  # blocks: the same windows (streaming is exact), small temporaries
            windows += det.update(t[i:i + _DETECT_BLOCK], raw[i:i + _DETECT_BLOCK],
                                  None if aux is None else aux[i:i + _DETECT_BLOCK])
    windows += det.flush()
    k = 0 if aux is None else (1 if np.ndim(aux) == 1 else np.shape(aux)[1])
    if not windows:
        return WindowSet(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0), np.zeros(0), np.zeros((0, k)),
                         np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
    return WindowSet.from_windows(windows)
