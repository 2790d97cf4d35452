"""The single-sample IMU line (the per-sample latency path) is byte for byte the block encoder's line."""
from __future__ import annotations

import json

import numpy as np
import pytest

from gravcal.core.samples import empty
from gravcal.daemon.protocol import encode_imu_joined


def _block(rng: np.random.Generator, n: int) -> np.ndarray:
    s = empty(n)
    s["seq"] = rng.integers(0, 1 << 16, n)
    s["t"] = rng.uniform(0, 1e5, n)
    s["tick"] = rng.integers(0, 1 << 32, n)
    s["t1"] = rng.integers(1, 1 << 15, (n, 4))
    s["t2"] = rng.integers(1 << 15, 1 << 16, (n, 2))
    s["gyro"] = rng.integers(0, 4096, n)
    s["temp"] = rng.uniform(-10, 50, n)
    s["vsupply"] = rng.uniform(4.5, 5.5, n)
    s["flags"] = rng.integers(0, 256, n)
    return s


CASES = ["plain", "gyro", "nan_acc", "t2_zero", "inf_temp", "codes"]


@pytest.mark.parametrize("raw", [False, True])
@pytest.mark.parametrize("case", CASES)
def test_one_sample_line_equals_block_line(case, raw):
    rng = np.random.default_rng(CASES.index(case) * 2 + raw)
    for _ in range(20):
        s = _block(rng, 3)
        acc = rng.normal(0, 9.8, (3, 3))
        gyro = rng.normal(0, 2, 3) if case == "gyro" else np.full(3, np.nan)
        static = rng.integers(0, 2, 3).astype(bool)
        if case == "nan_acc":
            acc[:, rng.integers(0, 3)] = np.nan
        elif case == "t2_zero":
            s["t2"][:, rng.integers(0, 2)] = 0
        elif case == "inf_temp":
            s["temp"] = -np.inf
        elif case == "codes":
            static = rng.integers(-3, 4, 3)
        block = encode_imu_joined(s, acc, gyro, static, raw=raw).splitlines(keepends=True)
        for i in range(3):
            one = encode_imu_joined(s[i:i + 1], acc[i:i + 1], gyro[i:i + 1], static[i:i + 1], raw=raw)
            assert one == block[i]
            json.loads(one)  # valid JSON: non-finite numbers are null
