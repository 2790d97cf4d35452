"""The plain correction a = K^-1 (raw - o), applied to every published sample.

Two forms that give the same bits: ``block`` on numpy arrays (N samples) and ``one`` on a single
SAMPLE_DTYPE record, which is the daemon's per-sample latency path, in C (_correctkernel.c: numpy's
per-call overhead on 1-row arrays would be most of the cost there). Both compute the duty cycle T1/T2
(NaN where T2 = 0, core.samples.duty_ratios), subtract the offset and sum (raw - o) times K^-T term by
term, left to right. An extended calibration (terms with covariates) goes through Calibration.apply instead.
"""
from __future__ import annotations

import math

import numpy as np

from ._correctkernel import correct_row
from .samples import raw_triad


class PlainCorrection:
    """a = scale * K^-1 (raw - o) for a plain (offset, sensitivity) calibration.

    offset (3,) [duty], sensitivity K (3, 3) [duty per g]; ``scale`` converts g to the output unit
    (e.g. standard gravity for m/s²). The inverse is taken once, here.
    """

    def __init__(self, offset: np.ndarray, sensitivity: np.ndarray, scale: float = 1.0):
        self.offset = np.ascontiguousarray(offset, dtype=float)
        self.kinv_t = np.ascontiguousarray(np.linalg.inv(np.asarray(sensitivity, dtype=float)).T * scale)

    def block(self, samples: np.ndarray) -> np.ndarray:
        """(N, 3) corrected triad of a SAMPLE_DTYPE block."""
        x = raw_triad(samples) - self.offset
        k = self.kinv_t
        return x[:, 0:1] * k[0] + x[:, 1:2] * k[1] + x[:, 2:3] * k[2]

    def one(self, row: np.ndarray, acc: np.ndarray, gyro: np.ndarray, gyro_bias: float = math.nan,
            gyro_sens: float = math.nan) -> int:
        """Correct one SAMPLE_DTYPE record ``row`` (a C-contiguous 1-row block): its triad into ``acc`` (3
        float64) and its gyro rate (counts - gyro_bias) / gyro_sens into ``gyro`` (1 float64; NaN while either
        is unknown), the bits :meth:`block` and the gyro's numpy form give. Returns the record's seq."""
        return correct_row(row, self.offset, self.kinv_t, gyro_bias, gyro_sens, acc, gyro)
