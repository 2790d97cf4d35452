"""The correction of each published sample, as one float64 vector for the compiled kernel.

A calibration corrects a sample as a = scale * (K + dK)^-1 (raw - o - do) (core/calibration.py
Calibration.apply), where every term of an extended calibration adds, per axis, its parameter times its
covariate's deviation to the offsets (do) or to the diagonal sensitivities (dK). :func:`correction_params`
packs a calibration into the vector the kernel reads (core/_correctkernel.h, CP_* below): K, o, K^-T and,
per covariate, the coefficients on the offsets and on the sensitivities, taken from each term's calibration
view (core/model/terms), so any term the online calibrator can publish (daemon/config.py ONLINE_TERMS) is
corrected per sample in C. The numpy references the kernel is tested against are Calibration.apply and
tests/support/correction_reference.py.
"""
from __future__ import annotations

import math

import numpy as np

from ._correctkernel import correct_rows
from .calibration import Calibration
from .model.effect import references
from .model.terms import calibration_view

# the vector's slots (core/_correctkernel.h)
COVARIATE_SLOTS = ("temp", "vsupply", "time", "accel")  # COV_TEMP .. COV_ACCEL
ON_SLOTS = ("offset", "sensitivity")  # ON_OFFSET, ON_SENSITIVITY
CP_OFFSET, CP_KINV_T, CP_K, CP_SCALE, CP_FS, CP_REF, CP_USES, CP_COEF = 0, 3, 12, 21, 22, 23, 26, 30
CP_N = CP_COEF + len(ON_SLOTS) * len(COVARIATE_SLOTS) * 3


class UncorrectableTerm(ValueError):
    """A calibration term the per-sample correction cannot apply (its rows need the samples' history)."""


def correction_params(cal: Calibration, scale: float = 1.0, fs: float = math.nan) -> np.ndarray:
    """The CP_N vector of ``cal`` for the kernel: ``scale`` converts g to the output unit (standard gravity for
    m/s²), ``fs`` [Hz] gives a record's time seq / fs (needed by a time term). The cross-axis term acts at the
    reference only, where K already holds it; a lagged term needs the samples' history (offline only) and is
    refused with UncorrectableTerm naming it."""
    k = np.asarray(cal.sensitivity, dtype=float).reshape(3, 3)
    v = np.zeros(CP_N)
    v[CP_OFFSET:CP_OFFSET + 3] = np.asarray(cal.offset, dtype=float)
    v[CP_KINV_T:CP_KINV_T + 9] = (np.linalg.inv(k).T * scale).ravel()
    v[CP_K:CP_K + 9] = k.ravel()
    v[CP_SCALE], v[CP_FS] = scale, fs
    terms = cal.extended_terms
    if not terms:
        return v
    refs = references(cal.metadata["extended"])
    v[CP_REF:CP_REF + 3] = refs["temp"], refs["vsupply"], refs["time"]
    params = cal.metadata.get("params") or {}
    values = iter(float(params[n]) for n in cal.extended_param_names)
    coef = v[CP_COEF:].reshape(len(ON_SLOTS), len(COVARIATE_SLOTS), 3)
    for term in terms:
        view = calibration_view(term)
        p = [next(values) for _ in range(3)]
        if view.acts_on == "cross":
            continue
        if view.lagged or view.acts_on not in ON_SLOTS or view.covariate not in COVARIATE_SLOTS:
            raise UncorrectableTerm(f"calibration {cal.model}: its term {term} needs the history of the samples "
                                    f"and cannot correct them one by one")
        cov = COVARIATE_SLOTS.index(view.covariate)
        v[CP_USES + cov] = 1.0
        coef[ON_SLOTS.index(view.acts_on), cov] += p
    if v[CP_USES + COVARIATE_SLOTS.index("time")] and not fs > 0:
        raise ValueError(f"calibration {cal.model}: its time term needs the sample rate")
    return v


def correct(params: np.ndarray, samples: np.ndarray, gyro_bias: float = math.nan,
            gyro_sens: float = math.nan) -> tuple[np.ndarray, np.ndarray]:
    """(acc (N, 3) in the params' unit, gyro (N,) [rad/s] as (counts - bias) / sens) of a SAMPLE_DTYPE block."""
    samples = np.ascontiguousarray(samples)
    n = samples.shape[0]
    acc, gyro = np.empty((n, 3)), np.empty(n)
    correct_rows(samples, params, gyro_bias, gyro_sens, acc, gyro)
    return acc, gyro
