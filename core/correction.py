"""The plain correction a = K^-1 (raw - o), applied to every published sample.

Two forms that give the same bits: ``block`` on numpy arrays (N samples) and ``one`` on Python
floats for a single sample, which is the daemon's per-sample latency path (numpy's per-call overhead
on 1-row arrays is most of the cost there). Both compute the duty cycle T1/T2 (NaN where T2 = 0,
core.samples.duty_ratios), subtract the offset and sum (raw - o) times K^-T term by term, left to
right. An extended calibration (terms with covariates) goes through Calibration.apply instead.
"""
from __future__ import annotations

import math

import numpy as np

from .samples import CHANNEL_CHIP, TRIAD, raw_triad

_TRIAD_CHIPS = [(c, int(CHANNEL_CHIP[c])) for c in TRIAD]  # (channel, index of its chip's period in t2)


class PlainCorrection:
    """a = scale * K^-1 (raw - o) for a plain (offset, sensitivity) calibration.

    offset (3,) [duty], sensitivity K (3, 3) [duty per g]; ``scale`` converts g to the output unit
    (e.g. standard gravity for m/s²). The inverse is taken once, here.
    """

    def __init__(self, offset: np.ndarray, sensitivity: np.ndarray, scale: float = 1.0):
        self.offset = np.asarray(offset, dtype=float)
        self.kinv_t = np.linalg.inv(np.asarray(sensitivity, dtype=float)).T * scale
        self._offset = self.offset.tolist()
        self._kinv = self.kinv_t.tolist()

    def block(self, samples: np.ndarray) -> np.ndarray:
        """(N, 3) corrected triad of a SAMPLE_DTYPE block."""
        x = raw_triad(samples) - self.offset
        k = self.kinv_t
        return x[:, 0:1] * k[0] + x[:, 1:2] * k[1] + x[:, 2:3] * k[2]

    def one(self, t1: list[float], t2: list[float]) -> list[float]:
        """The corrected triad [3] of one sample, from its T1 (per channel) and T2 (per chip) counts."""
        o, k = self._offset, self._kinv
        x = []
        for i, (c, chip) in enumerate(_TRIAD_CHIPS):
            period = t2[chip]
            x.append((t1[c] / period if period else math.nan) - o[i])
        return [x[0] * k[0][j] + x[1] * k[1][j] + x[2] * k[2][j] for j in range(3)]
