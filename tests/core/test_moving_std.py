"""core/detectors/_movingstd.c: the moving-variance detector's signal equals its numpy reference
(core/detectors/_movingstd_reference.py: running sums of the increments after the carried sums, the ddof=1
variance, np.maximum over the axes and at 0, np.sqrt) bit for bit, and a bad buffer is a clear error, never a crash.

Random blocks: window lengths 2-250, block lengths 0 to 300 000, values spanning magnitudes (so a change in
the order of the sums changes the rounding somewhere), constant stretches (variances of exactly 0), and
non-finite increments (NaN propagated as numpy's maximum does)."""
from __future__ import annotations

import numpy as np
import pytest

from gravcal.core.detectors import variance
from gravcal.core.detectors._movingstd import moving_std
from gravcal.core.detectors._movingstd_reference import moving_std as numpy_moving_std
from gravcal.core.detectors.variance import MovingVarianceDetector
from gravcal.core.estimators.start import bootstrap


def random_ext(rng: np.random.Generator, w: int, n: int) -> np.ndarray:
    y = rng.standard_normal((3, w + n)) * 10.0 ** rng.integers(-4, 5, size=(3, 1)) + rng.standard_normal((3, 1)) * 50
    if n > 10:  # constant stretches: increments of exactly 0
        k = int(rng.integers(0, n // 2))
        y[:, w + k:w + k + n // 4] = y[:, w + k:w + k + 1]
    return np.ascontiguousarray(np.concatenate([y, y * y]))


@pytest.mark.parametrize("w, n", [(2, 0), (2, 1), (25, 7), (25, 8192), (100, 300_000), (250, 999), (7, 5000)])
def test_signal_equals_numpy_bit_for_bit(w, n):
    rng = np.random.default_rng(w * 1000 + n)
    for _ in range(3):
        ext = random_ext(rng, w, n)
        sums = rng.standard_normal(6) * 10.0 ** rng.integers(-3, 4, size=6)
        want_sums, want = sums.copy(), np.empty(n)
        numpy_moving_std(ext, w, want_sums, want)
        got_sums, got = sums.copy(), np.full(n, 7.0)
        moving_std(ext, w, got_sums, got)
        assert np.array_equal(got, want) and np.array_equal(np.signbit(got), np.signbit(want))
        assert np.array_equal(got_sums, want_sums)


def test_non_finite_values_propagate_as_numpy():
    rng = np.random.default_rng(5)
    w, n = 10, 400
    ext = random_ext(rng, w, n)
    ext[1, w + 50] = np.nan
    ext[4, w + 200] = np.inf
    ext[0, w + 300] = -np.inf
    sums = np.zeros(6)
    want_sums, want = sums.copy(), np.empty(n)
    with np.errstate(invalid="ignore"):  # inf - inf in the oracle's running sums is the point of this case
        numpy_moving_std(ext, w, want_sums, want)
    got_sums, got = sums.copy(), np.empty(n)
    moving_std(ext, w, got_sums, got)
    assert np.isnan(want).any()
    assert np.array_equal(got, want, equal_nan=True) and np.array_equal(got_sums, want_sums, equal_nan=True)


def test_signed_zeros_come_out_as_numpy():
    """Variances of exactly ±0 on every axis: numpy's maximum and clip decide the sign of the zero."""
    rng = np.random.default_rng(8)
    w, n = 4, 2000
    cases = [np.where(rng.random((6, w + n)) < 0.5, -0.0, 0.0) for _ in range(3)]
    cases[0][:, :w], cases[0][:, w:] = 0.0, -0.0  # the first w increments -0 - (+0) = -0: variances -0 - (+0) / w
    for ext, sums in zip(cases, (np.full(6, -0.0), np.zeros(6), np.where(rng.random(6) < 0.5, -0.0, 0.0))):
        want_sums, want = sums.copy(), np.empty(n)
        numpy_moving_std(ext, w, want_sums, want)
        got_sums, got = sums.copy(), np.empty(n)
        moving_std(ext, w, got_sums, got)
        assert np.array_equal(np.signbit(got), np.signbit(want)) and np.array_equal(got, want)
        assert np.array_equal(np.signbit(got_sums), np.signbit(want_sums))


def test_detector_streams_equal_the_numpy_form(monkeypatch):
    """The whole detector (windows and signal), fed in random pieces with non-finite rows and gaps, equals the
    same detector running the numpy form."""
    rng = np.random.default_rng(11)
    n, fs = 40_000, 100.0
    t = np.arange(n) / fs
    t[25_000:] += 3.0  # a gap
    raw = np.repeat(rng.standard_normal((n // 500, 3)) * 300 + 2000, 500, axis=0)
    raw += rng.standard_normal((n, 3)) * np.repeat(rng.choice([1.0, 40.0], n // 500), 500)[:, None]
    raw[rng.choice(n, 30, replace=False), rng.integers(0, 3, 30)] = np.nan

    cuts = np.sort(rng.choice(n, 40, replace=False))

    def run() -> tuple[list, np.ndarray]:
        det = MovingVarianceDetector(fs, window_s=1.0, threshold_g=5.0, min_duration_s=2.0, max_duration_s=None)
        out, sig = [], []
        for i, j in zip([0, *cuts], [*cuts, n]):
            out += det.update(t[i:j], raw[i:j])
            sig.append(det.last_detection)
        return out + det.flush(), np.concatenate(sig)

    got, got_sig = run()
    monkeypatch.setattr(variance, "moving_std", numpy_moving_std)
    want, want_sig = run()
    assert len(got) == len(want) > 5
    assert np.array_equal(got_sig, want_sig, equal_nan=True)
    for a, b in zip(got, want):
        assert (a.start, a.end) == (b.start, b.end)
        assert np.array_equal(a.mean, b.mean) and np.array_equal(a.cov, b.cov)


def test_bootstrap_equals_the_numpy_form(monkeypatch):
    """bootstrap (the noise-floor probe and the still segments both run the detector) gives the same start."""
    rng = np.random.default_rng(3)
    poses = rng.standard_normal((60, 3))
    poses /= np.linalg.norm(poses, axis=1, keepdims=True)
    raw = np.repeat(poses, 1000, axis=0) * np.array([400.0, 380.0, 420.0]) + np.array([2000.0, 2100.0, 1900.0])
    raw += rng.standard_normal(raw.shape) * np.repeat(rng.choice([2.0, 60.0], 60), 1000)[:, None]
    t = np.arange(raw.shape[0]) / 100.0
    got = bootstrap(t, raw, 100.0)
    monkeypatch.setattr(variance, "moving_std", numpy_moving_std)
    want = bootstrap(t, raw, 100.0)
    assert got.metadata["noise_floor_raw"] == want.metadata["noise_floor_raw"]
    assert got.n_windows == want.n_windows > 6
    assert np.array_equal(got.offset, want.offset) and np.array_equal(got.sensitivity, want.sensitivity)


@pytest.mark.parametrize("args, kind, match", [
    ((np.zeros((6, 10)), 1, np.zeros(6), np.zeros(9)), ValueError, "at least 2 samples"),
    ((np.zeros((6, 10)), 11, np.zeros(6), np.zeros(0)), ValueError, r"ext must be \(6, 11 \+ n\)"),
    ((np.zeros((5, 10)), 2, np.zeros(6), np.zeros(8)), ValueError, r"ext must be \(6"),
    ((np.zeros((6, 10)), 2, np.zeros(5), np.zeros(8)), ValueError, "sums must hold 6 items"),
    ((np.zeros((6, 10)), 2, np.zeros(6), np.zeros(9)), ValueError, "det must hold 8 items"),
    ((np.zeros((6, 10), dtype=np.float32), 2, np.zeros(6), np.zeros(8)), TypeError, "ext must hold float64"),
    ((np.zeros((10, 6)).T, 2, np.zeros(6), np.zeros(8)), TypeError, "ext must be a C-contiguous"),
    ((np.zeros((6, 10)), 2, np.zeros(6), np.zeros(8)), None, None),
    ((np.zeros((6, 10)), 2, np.zeros(6), np.zeros(16)[::2]), TypeError, "det must be a C-contiguous writable"),
    (("abc", 2, np.zeros(6), np.zeros(8)), TypeError, "ext must be a C-contiguous"),
])
def test_bad_buffers_are_clear_errors(args, kind, match):
    if kind is None:
        moving_std(*args)  # the right buffers are accepted
        return
    with pytest.raises(kind, match=match):
        moving_std(*args)
    ro = np.zeros(6)
    ro.flags.writeable = False
    with pytest.raises(TypeError, match="sums must be a C-contiguous writable"):
        moving_std(np.zeros((6, 10)), 2, ro, np.zeros(8))
