"""The IMU lines of the line kernel (daemon/_linekernel.c), one sample or a block, are byte for byte those of its
numpy reference (tests/support/line_reference.py: Python's %-formatting)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from gravcal.core.samples import empty
from gravcal.daemon.protocol import encode_imu_joined
from support.line_reference import imu_lines as reference


def reference_lines(s, acc, gyro, static, *, raw):
    """The reference's lines of a block, once the kernel's block is checked to be the same bytes."""
    want = reference(s, acc, gyro, static, raw=raw)
    assert encode_imu_joined(s, acc, gyro, static, raw=raw) == want
    return want.splitlines(keepends=True)


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
        block = reference_lines(s, acc, gyro, static, raw=raw)
        for i in range(3):
            one = encode_imu_joined(s[i:i + 1], acc[i:i + 1], gyro[i:i + 1], static[i:i + 1], raw=raw)
            assert one == block[i]
            json.loads(one)  # valid JSON: non-finite numbers are null


EDGE_FLOATS = [0.0, -0.0, -1e-9, 0.5e-5, -0.5e-5, 1e300, -1.7976931348623157e308, 5e-324, np.nan, np.inf, -np.inf,
               123456.7890125, 2.5e-6]


@pytest.mark.parametrize("raw", [False, True])
def test_one_sample_line_equals_block_line_on_edge_values(raw):
    """Every float field on extreme, signed-zero, rounding-tie and non-finite values, integer fields at their
    limits and static codes far outside -1..1: the C line is the reference's, byte for byte."""
    rng = np.random.default_rng(7)
    n = 400
    s = _block(rng, n)
    pick = lambda: rng.choice(EDGE_FLOATS, n)  # noqa: E731
    s["t"] = pick()
    s["temp"] = rng.choice([0.0, -0.0, 3.4e38, -3.4e38, 0.005, np.nan, np.inf, -np.inf, 21.125], n)
    s["vsupply"] = rng.choice([0.0, 1e-4, 0.0005, 5.0, np.nan, np.inf], n)
    s["seq"] = rng.choice([0, -1, 2**63 - 1, -2**63, 65535], n)
    s["tick"] = rng.choice([0, 2**32 - 1], n)
    s["t1"] = rng.choice([0, 1, 2**32 - 1], (n, 4))
    s["t2"] = rng.choice([0, 1, 2**32 - 1], (n, 2))
    s["gyro"] = rng.choice([0, 65535], n)
    s["flags"] = rng.choice([0, 65535], n)
    acc = rng.choice(EDGE_FLOATS, (n, 3))
    gyro = rng.choice(EDGE_FLOATS, n)
    for static in (rng.choice([-2**62, -300, -1, 0, 1, 2, 300, 2**62], n), rng.integers(0, 2, n).astype(bool),
                   rng.integers(-1, 2, n).astype(np.int8)):
        block = reference_lines(s, acc, gyro, static, raw=raw)
        for i in range(n):
            one = encode_imu_joined(s[i:i + 1], acc[i:i + 1], gyro[i:i + 1], static[i:i + 1], raw=raw)
            assert one == block[i]
            json.loads(one)


def test_line_kernel_rejects_wrong_buffers_with_a_clear_error():
    from gravcal.daemon._linekernel import imu_line

    row = empty(1)
    with pytest.raises(ValueError, match="56-byte SAMPLE_DTYPE"):
        imu_line(row.tobytes()[:40], np.zeros(3), 0.0, 1, True)
    with pytest.raises(ValueError, match="3 float64"):
        imu_line(row, np.zeros(2), 0.0, 1, True)
    with pytest.raises(TypeError):
        imu_line(row, np.zeros(3), 0.0, "still", True)
    with pytest.raises(ValueError, match="not C-contiguous"):  # refused by the buffer protocol: nothing read
        imu_line(row, np.zeros(6)[::2], 0.0, 1, True)


def _random_doubles(rng: np.random.Generator, n: int) -> np.ndarray:
    """Finite doubles over every binary exponent (random bit patterns), and dyadic fractions a / 2^b, many of
    them exact rounding ties at 2, 3, 5 and 6 decimals (0.125, 0.015625, ...)."""
    bits = rng.integers(0, 1 << 63, n, dtype=np.uint64) | (rng.integers(0, 2, n, dtype=np.uint64) << np.uint64(63))
    wide = bits.view(np.float64)
    wide = wide[np.isfinite(wide)]
    near = rng.integers(-(1 << 20), 1 << 20, n) / 2.0 ** rng.integers(0, 30, n)
    scaled = rng.normal(0, 1, n) * 10.0 ** rng.integers(-12, 19, n)  # the decimal range lines carry, and beyond
    return np.concatenate([wide, near, scaled])


def test_fixed_decimals_are_pythons_on_every_exponent_and_tie():
    """The line's %.Nf numbers, written in integer arithmetic where they fit, are Python's %-formatting's (the
    reference's) digit for digit on random bit patterns, dyadic ties and values up to 1e19 and beyond."""
    rng = np.random.default_rng(11)
    x = _random_doubles(rng, 3000)
    n = x.size // 3 * 3
    s = _block(rng, n)
    s["t"] = rng.permutation(x)[:n]
    x32 = x[np.abs(x) < 3e38].astype(np.float32)
    s["temp"] = rng.choice(x32, n)
    s["vsupply"] = rng.choice(x32, n)
    acc = rng.permutation(x)[:n].reshape(-1, 3).repeat(3, axis=0)[:n]
    gyro = rng.permutation(x)[:n]
    static = rng.integers(0, 2, n).astype(bool)
    block = reference_lines(s, acc, gyro, static, raw=True)
    for i in range(n):
        assert encode_imu_joined(s[i:i + 1], acc[i:i + 1], gyro[i:i + 1], static[i:i + 1], raw=True) == block[i]
