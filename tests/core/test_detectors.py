"""Quasi-static detectors: planted still/moving segments, block invariance, splitting, NaN, gaps."""
from functools import lru_cache

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gravcal.core.calibration import Calibration
from gravcal.core.detectors import MovingVarianceDetector, QuasiStaticDetector, detect

from filter_bounds import cascade_gains, sosfilt_difference_bound
from gravcal.core.butterworth import sos_rest_state

FS = 100.0
NOISE_G = 0.0045  # ADXL210 500 µg/√Hz over ~80 Hz noise bandwidth, per axis [g]


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def make_stream(rng, n_postures=6, still_s=8.0, move_s=3.0, shake_g=0.25, noise_g=NOISE_G, fs=FS, postures=None):
    """Specific force [g] for still postures joined by movements: during a movement the
    orientation turns smoothly to the next posture while the body shakes (2 Hz, shake_g).
    Returns t, f (N, 3), the true still intervals [(a, b)] in samples, and the postures."""
    postures = _unit(rng.normal(size=(n_postures, 3))) if postures is None else _unit(np.asarray(postures, float))
    n_postures = postures.shape[0]
    ns, nm = int(still_s * fs), int(move_s * fs)
    parts, still = [], []
    for i, p in enumerate(postures):
        start = sum(len(x) for x in parts)
        parts.append(np.repeat(p[None], ns, axis=0))
        still.append((start, start + ns))
        if i + 1 < n_postures:
            tau = np.arange(nm) / nm
            s = tau * tau * (3 - 2 * tau)  # smoothstep turn
            turn = _unit((1 - s)[:, None] * p + s[:, None] * postures[i + 1])
            phase = 2 * np.pi * 2.0 * np.arange(nm) / fs
            shake = shake_g * np.column_stack([np.sin(phase), np.cos(1.3 * phase), np.sin(0.7 * phase)])
            parts.append(turn + shake)
    f = np.concatenate(parts)
    f = f + rng.normal(0.0, noise_g, f.shape)
    t = np.arange(f.shape[0]) / fs
    return t, f, still, postures


def _run_blocks(det, t, raw, aux, sizes):
    out, i = [], 0
    for s in sizes:
        out += det.update(t[i:i + s], raw[i:i + s], None if aux is None else aux[i:i + s])
        i = min(i + s, t.shape[0])
    out += det.update(t[i:], raw[i:], None if aux is None else aux[i:])
    return out + det.flush()


def _assert_same_windows(a, b):
    assert [(w.start, w.end, w.t_start, w.t_end) for w in a] == [(w.start, w.end, w.t_start, w.t_end) for w in b]
    for wa, wb in zip(a, b):
        # sums are grouped differently per block split: equal up to rounding
        np.testing.assert_allclose(wa.mean, wb.mean, rtol=1e-12, atol=0)
        np.testing.assert_allclose(wa.cov, wb.cov, rtol=1e-8, atol=1e-12 * np.abs(wb.cov).max())
        np.testing.assert_allclose(wa.aux_mean, wb.aux_mean, rtol=1e-12)


@lru_cache(maxsize=None)
def _invariance_stream():
    """40 s in counts with NaNs, a dropout, a temperature aux channel."""
    rng = np.random.default_rng(7)
    t, f, _, _ = make_stream(rng, n_postures=4, still_s=7.0, move_s=2.0)
    raw = 4096.0 * f + 32768.0
    raw[rng.choice(raw.shape[0], 12, replace=False), rng.integers(0, 3, 12)] = np.nan
    t = t.copy()
    t[1500:] += 0.3  # dropout of 30 samples
    aux = 25.0 + 0.01 * np.arange(t.shape[0])[:, None] / FS
    return t, raw, aux


CAL_COUNTS = Calibration.nominal(np.full(3, 32768.0), 4096.0)
DETECTOR_KW = dict(min_duration_s=0.5, max_duration_s=1.7, guard_s=0.3, to_g=CAL_COUNTS)


@pytest.mark.parametrize("cls", [QuasiStaticDetector, MovingVarianceDetector])
@settings(max_examples=40, deadline=None)
@given(sizes=st.lists(st.one_of(st.integers(0, 3), st.integers(0, 700)), min_size=0, max_size=60))
def test_any_block_split_gives_the_same_windows(cls, sizes):
    t, raw, aux = _invariance_stream()
    det = cls(FS, **DETECTOR_KW)
    whole = det.update(t, raw, aux) + det.flush()
    assert len(whole) >= 10  # the stream must exercise splitting, NaN and the gap
    _assert_same_windows(_run_blocks(det, t, raw, aux, sizes), whole)


@pytest.mark.parametrize("cls", [QuasiStaticDetector, MovingVarianceDetector])
def test_single_sample_blocks_give_the_same_windows(cls):
    t, raw, aux = _invariance_stream()
    n = 1800
    det = cls(FS, **DETECTOR_KW)
    whole = det.update(t[:n], raw[:n], aux[:n]) + det.flush()
    assert len(whole) >= 4
    _assert_same_windows(_run_blocks(det, t[:n], raw[:n], aux[:n], [1] * n), whole)


# Edge tolerances. The end of a still period is found by the detection signal rising
# (shake 0.25 g crosses 20 mg within ~0.1 s) and is trimmed by guard_s, so windows end
# within guard + 0.5 s before the true end and never after it. The start waits for the
# detection signal to decay (Lötters: the 0.5 Hz low-pass, ~1.5 s) or for the trailing
# variance window to clear the movement (window_s), plus the guard.
@pytest.mark.parametrize("method,start_tol_s,end_tol_s", [("lotters", 3.0, 1.0), ("variance", 1.0 + 0.25 + 0.3, 0.75)])
def test_windows_match_planted_still_segments(method, start_tol_s, end_tol_s):
    rng = np.random.default_rng(3)
    t, f, still, postures = make_stream(rng, n_postures=8)
    ws = detect(t, f, method=method, fs=FS, max_duration_s=None)
    for s, e in zip(ws.start, ws.end):  # no window touches a movement
        assert any(a <= s and e <= b for a, b in still), (s, e)
    for k, (a, b) in enumerate(still):
        inside = (ws.start >= a) & (ws.end <= b)
        if k == 0 and method == "lotters":  # filters settle first (~4.7 s), nothing to check at the start
            assert inside.sum() == 1 and ws.end[inside][0] >= b - end_tol_s * FS
            continue
        assert inside.sum() == 1, (a, b, ws.start, ws.end)
        (s,), (e,) = ws.start[inside], ws.end[inside]
        assert a <= s <= a + start_tol_s * FS
        assert b - end_tol_s * FS <= e <= b
        m = ws.mean[inside][0]  # the window's mean is the planted posture within its noise
        assert np.linalg.norm(m - postures[k]) < 5 * NOISE_G * np.sqrt(3.0 / (e - s))
        np.testing.assert_allclose(np.diag(ws.cov[inside][0]), NOISE_G ** 2, rtol=0.35)


@pytest.mark.parametrize("cls", [QuasiStaticDetector, MovingVarianceDetector])
def test_long_still_period_is_split_at_max_duration(cls):
    rng = np.random.default_rng(1)
    n = int(300 * FS)
    f = np.array([0.0, 0.6, 0.8]) + rng.normal(0, NOISE_G, (n, 3))
    t = np.arange(n) / FS
    det = cls(FS, max_duration_s=60.0, min_duration_s=5.0)
    windows = det.update(t, f) + det.flush()
    settle = det.settle_n if cls is QuasiStaticDetector else det.w - 1
    first, last = settle + det.guard, n - det.guard  # still from settling to the end; guard trims both ends
    max_n = 6000
    n_full, rest = divmod(last - first, max_n)
    expected = [(first + k * max_n, first + (k + 1) * max_n) for k in range(n_full)]
    if rest >= det.min_n:
        expected.append((first + n_full * max_n, last))
    assert [(w.start, w.end) for w in windows] == expected
    assert len(windows) >= 4
    for w in windows:
        np.testing.assert_allclose(w.mean, [0.0, 0.6, 0.8], atol=5 * NOISE_G / np.sqrt(w.n))


@pytest.mark.parametrize("cls", [QuasiStaticDetector, MovingVarianceDetector])
def test_nonfinite_samples_end_windows_and_are_counted(cls):
    rng = np.random.default_rng(2)
    n = int(60 * FS)
    f = np.array([0.0, 0.0, 1.0]) + rng.normal(0, NOISE_G, (n, 3))
    bad = np.array([3000, 4500])
    f[bad[0], 1] = np.nan
    f[bad[1], 0] = np.inf
    t = np.arange(n) / FS
    det = cls(FS, max_duration_s=None)
    windows = det.update(t, f) + det.flush()
    assert det.counts["nonfinite"] == 2 and det.counts["samples"] == n
    assert len(windows) == 3  # the two bad samples cut one still period into three
    for w in windows:
        assert not np.any((bad >= w.start - det.guard) & (bad < w.end + det.guard))
        assert np.all(np.isfinite(w.mean)) and np.all(np.isfinite(w.cov))
    assert windows[1].start == bad[0] + 1 + det.guard and windows[1].end == bad[1] - det.guard


def test_time_gap_ends_a_window():
    rng = np.random.default_rng(4)
    n = int(40 * FS)
    f = np.array([0.0, 0.0, 1.0]) + rng.normal(0, NOISE_G, (n, 3))
    t = np.arange(n) / FS
    t[2500:] += 2.0  # 2 s dropout before sample 2500
    det = QuasiStaticDetector(FS, max_duration_s=None)
    windows = det.update(t, f) + det.flush()
    assert det.counts["gaps"] == 1
    assert [w.end for w in windows][0] == 2500 - det.guard
    assert windows[1].start == 2500 + 1 + det.guard


def test_calibration_to_g_makes_thresholds_in_g():
    """Counts with a calibration give the windows of the same data in g."""
    rng = np.random.default_rng(5)
    t, f, _, _ = make_stream(rng, n_postures=5)
    cal = Calibration.nominal(np.array([32768.0, 32000.0, 33000.0]), np.array([4096.0, 4000.0, 4200.0]))
    raw = f * np.array([4096.0, 4000.0, 4200.0]) + cal.offset
    in_g = detect(t, f, fs=FS)
    in_counts = detect(t, raw, fs=FS, to_g=cal)
    assert len(in_g) >= 4
    np.testing.assert_array_equal(in_counts.start, in_g.start)
    np.testing.assert_array_equal(in_counts.end, in_g.end)
    np.testing.assert_allclose(cal.apply(in_counts.mean), in_g.mean, atol=1e-9)
    # without to_g the 20 mg threshold is 20 mcounts: nothing is ever still
    assert len(detect(t, raw, fs=FS)) == 0


def test_to_g_is_settable_and_accepts_a_callable():
    rng = np.random.default_rng(6)
    t, f, _, _ = make_stream(rng, n_postures=3)
    raw = 4096.0 * f + 32768.0
    det = QuasiStaticDetector(FS)
    assert det.to_g is None
    det.to_g = lambda r: (r - 32768.0) / 4096.0
    ws = det.update(t, raw) + det.flush()
    ref = detect(t, f, fs=FS)
    assert [(w.start, w.end) for w in ws] == list(zip(ref.start, ref.end))


def test_aux_means_and_fs_estimate():
    rng = np.random.default_rng(8)
    t, f, _, _ = make_stream(rng, n_postures=3)
    temp = 20.0 + 0.1 * t  # warming at 0.1 °C/s
    ws = detect(t, f, aux=temp)  # fs estimated from t
    assert ws.aux.shape == (len(ws), 1) and len(ws) >= 2
    mid = 0.5 * (ws.start + ws.end - 1) / FS
    np.testing.assert_allclose(ws.aux[:, 0], 20.0 + 0.1 * mid, rtol=1e-9)


def test_bad_input_is_named():
    det = QuasiStaticDetector(FS)
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        det.update(np.zeros(4), np.zeros((4, 2)))
    with pytest.raises(ValueError, match="t has 3 samples"):
        det.update(np.zeros(3), np.zeros((4, 3)))
    det.update(np.arange(4) / FS, np.zeros((4, 3)), np.zeros((4, 2)))
    with pytest.raises(ValueError, match="aux has 1 channels"):
        det.update(np.arange(4, 8) / FS, np.zeros((4, 3)), np.zeros((4, 1)))
    with pytest.raises(ValueError, match="unknown detector method"):
        detect(np.arange(10.0), np.zeros((10, 3)), method="magic")
    with pytest.raises(ValueError, match="shorter than min_duration_s"):
        MovingVarianceDetector(FS, min_duration_s=5, max_duration_s=2)
    with pytest.raises(ValueError, match="sample rate"):
        QuasiStaticDetector(0.0)
    with pytest.raises(ValueError, match="cannot estimate the sample rate"):
        detect(np.zeros(5), np.zeros((5, 3)))


def test_per_axis_channels_see_turns_that_keep_the_norm():
    """A calibrated norm is 1 g in every orientation: eq. 1 alone merges a slow turn into a
    window (the paper's detector ran on uncalibrated voltages); the per-axis channels don't."""
    rng = np.random.default_rng(9)
    quarter_turns = [[0, 0, 1], [1, 0, 0], [0, 1, 0], [0, 0, -1], [-1, 0, 0], [0, -1, 0]]
    t, f, still, postures = make_stream(rng, shake_g=0.0, postures=quarter_turns)  # pure 90° turns in 3 s
    good = detect(t, f, fs=FS, max_duration_s=None)
    paper = detect(t, f, fs=FS, max_duration_s=None, per_axis=False)
    # a smoothstep turn starts at zero speed: in its first 0.4 s it turns < 5°, and the few
    # samples a window takes from it move the window mean by < 1 mg
    for s, e in zip(good.start, good.end):
        assert any(a <= s and e <= b + 0.4 * FS for a, b in still), (s, e)
    assert len(good) == len(still)
    assert np.all(np.abs(np.linalg.norm(good.mean, axis=1) - 1) < 5 * NOISE_G / np.sqrt(good.n))
    spans_turn = [not any(a <= s and e <= b for a, b in still) for s, e in zip(paper.start, paper.end)]
    assert any(spans_turn) and len(paper) < len(still)


@pytest.mark.parametrize("cls,max_s", [(QuasiStaticDetector, 60.0), (QuasiStaticDetector, 1.7), (MovingVarianceDetector, 1.7)])
def test_window_statistics_are_those_of_its_samples(cls, max_s):
    """Means/covariances from the running sums equal numpy's over the window's samples, both
    for long windows (one dot product per sum) and many short ones (reduceat over the block)."""
    t, raw, aux = _invariance_stream()
    det = cls(FS, **{**DETECTOR_KW, "max_duration_s": max_s})
    windows = _run_blocks(det, t, raw, aux, [5000])
    assert len(windows) >= 4
    for w in windows:
        x = raw[w.start:w.end]
        assert np.all(np.isfinite(x)) and w.t_start == t[w.start] and w.t_end == t[w.end - 1]
        np.testing.assert_allclose(w.mean, x.mean(axis=0), rtol=1e-12)
        np.testing.assert_allclose(w.cov, np.cov(x.T), rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(w.aux_mean, aux[w.start:w.end].mean(axis=0), rtol=1e-12)


def test_threads_fortran_input_and_scipys_sosfilt_give_identical_results(monkeypatch):
    """threads=2 splits the channels between threads and Fortran-ordered raw skips a transpose: neither may
    change a bit. scipy.signal.sosfilt in place of the compiled kernel is the filter's reference: its detection
    signal within the rounding bound of the two filters (tests/core/filter_bounds.py), never SciPy's bits, and
    (no sample that close to the threshold) the same windows."""
    from scipy import signal

    from gravcal.core.detectors import windowing

    def scipy_sosfilt(sos, x, zi):
        y, z = signal.sosfilt(sos, x, axis=-1, zi=np.moveaxis(zi, 1, 0))
        x[...] = y
        zi[...] = np.moveaxis(z, 0, 1)

    rng = np.random.default_rng(11)
    t, f, _, _ = make_stream(rng, n_postures=12, still_s=60.0)
    raw = 4096.0 * f + 32768.0
    kw = dict(to_g=CAL_COUNTS, max_duration_s=20.0)

    def run(raw, **extra):
        det = QuasiStaticDetector(FS, **kw, **extra)
        out, dets = [], []
        for i in range(0, t.shape[0], 20000):
            out += det.update(t[i:i + 20000], raw[i:i + 20000])
            dets.append(det.last_detection)
        return out + det.flush(), np.concatenate(dets)

    ref, ref_det = run(raw)
    assert len(ref) >= 12
    variants = [run(raw, threads=2), run(np.asfortranarray(raw))]
    monkeypatch.setattr(windowing, "sosfilt", scipy_sosfilt)
    variants.append(run(raw))
    probe = QuasiStaticDetector(FS, **kw)
    u_max = float(max(np.linalg.norm(f, axis=1).max(), np.abs(f).max())) * 1.01  # |a| and the axes [g]
    hp, lp = probe.sos_hp, probe.sos_lp
    bound = (sosfilt_difference_bound(hp, u_max, u_max * np.abs(sos_rest_state(hp)).max()) * cascade_gains(lp)[0]
             + sosfilt_difference_bound(lp, u_max * (1 + cascade_gains(hp)[0]), 0.0))
    assert bound < 1e-3 * probe.threshold_g and np.all(np.abs(ref_det - probe.threshold_g) > bound)
    for k, (windows, det) in enumerate(variants):
        if k < 2:
            np.testing.assert_array_equal(det, ref_det)
        else:
            assert np.max(np.abs(det - ref_det)) <= bound
        assert [(w.start, w.end) for w in windows] == [(w.start, w.end) for w in ref]
        for a, b in zip(windows, ref):
            np.testing.assert_allclose(a.mean, b.mean, rtol=1e-14)
            np.testing.assert_allclose(a.cov, b.cov, rtol=1e-9)
