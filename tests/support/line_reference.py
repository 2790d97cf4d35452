"""The numpy reference of the IMU line encoder (daemon/_linekernel.c), the oracle its tests compare it to.

The whole block is formatted by ONE ``%`` operation over a template repeated N times and a flat tuple of the
values, built column-wise by numpy; non-finite numbers become the word null (JSON has none). The line kernel
writes the same bytes (each %.Nf as Python's % writes it, each %d the integer)."""
from __future__ import annotations

from typing import Any

import numpy as np

from gravcal.core.samples import duty_ratios

HEAD_FIELDS = '{"class":"IMU","seq":%d,"t":%.6f,"acc":[%.5f,%.5f,%.5f],"gyro":{gyro},"static":%s,"temp":%.2f,"vsupply":%.3f'
RAW_FIELDS = ',"duty":[%.6f,%.6f,%.6f,%.6f],"t1":[%d,%d,%d,%d],"t2":[%d,%d],"gyro_counts":%d,"tick":%d,"flags":%d}\n'
# How % writes non-finite floats; no key or word of an IMU line contains these letters, so replacing them
# touches only numbers.
NON_FINITE_WORDS = (b"-inf", b"inf", b"nan")


def static_words(static: np.ndarray, n: int) -> np.ndarray:
    """The JSON words of ``static``: a bool array, or int codes 1 (still), 0 (moving), <= -1 (null)."""
    st = np.asarray(static).reshape(n)
    if st.dtype == bool:
        return np.where(st, "true", "false")
    return np.array(["null", "false", "true"])[np.clip(st.astype(np.int64), -1, 1) + 1]


def imu_lines(samples: np.ndarray, acc_ms2: np.ndarray, gyro_rads: np.ndarray, static: np.ndarray, *,
              raw: bool = False) -> bytes:
    n = samples.shape[0]
    acc = np.asarray(acc_ms2, dtype=float).reshape(n, 3)
    gyro = np.asarray(gyro_rads, dtype=float).reshape(n)
    gyro_null = bool(np.isnan(gyro).all())  # the usual uncalibrated gyro: a literal null
    cols: list[Any] = [samples["seq"], samples["t"], acc[:, 0], acc[:, 1], acc[:, 2]]
    if not gyro_null:
        cols.append(gyro)
    cols += [static_words(static, n), samples["temp"], samples["vsupply"]]
    template = HEAD_FIELDS.replace("{gyro}", "null" if gyro_null else "%.6f")
    if raw:
        duty = duty_ratios(samples)
        cols += [duty[:, 0], duty[:, 1], duty[:, 2], duty[:, 3], *samples["t1"].T, *samples["t2"].T,
                 samples["gyro"], samples["tick"], samples["flags"]]
        template += RAW_FIELDS
    else:
        template += "}\n"
    table = np.empty((n, len(cols)), dtype=object)
    for j, c in enumerate(cols):
        table[:, j] = c  # numpy converts to Python int/float/str
    text = ((template * n) % tuple(table.ravel().tolist())).encode()
    for word in NON_FINITE_WORDS:
        text = text.replace(word, b"null")
    return text
