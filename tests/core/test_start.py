"""Starting points: ellipsoid fit of window means, and the scale-free bootstrap."""
import numpy as np
import pytest

from gravcal.core.estimators.start import ellipsoid_fit, bootstrap
from gravcal.core.windows import WindowSet

K_DIAG = np.array([0.041, 0.039, 0.043])  # duty cycle per g (ADXL210 ~4 %/g, spread between axes)
OFFSET = np.array([0.50, 0.49, 0.51])  # duty cycle at 0 g
NOISE_G = 0.0045  # per-axis sample noise [g]


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _points(rng, m, sigma_g, K=np.diag(K_DIAG), o=OFFSET):
    """m window means on the ellipsoid raw = K a + o, a uniform on the sphere, noise sigma_g [g] per axis."""
    a = _unit(rng.normal(size=(m, 3)))
    return (a + rng.normal(0.0, sigma_g, (m, 3))) @ K.T + o


def test_ellipsoid_fit_error_matches_the_noise():
    # Linearised LS on the sphere with directions uniform: the norm residual has std sigma, so
    # std(o_k / s_k) = sigma sqrt(3/M) and std(ds_k / s_k) = sigma sqrt(6/M) (information matrix
    # M/3 I for offsets and M/15 (2 I + 1 1^T) for sensitivities). 20 seeds x 3 axes: the RMS is
    # known to ~9 %; the robust weights cost a few % efficiency and M = 40 random directions are
    # not quite uniform (measured ratio ~1.1 over 200 seeds), so [0.7, 1.5] is a ~4-sigma band.
    m, sigma = 40, 1e-3
    eo, es = [], []
    for seed in range(20):
        cal = ellipsoid_fit(WindowSet.from_points(_points(np.random.default_rng(seed), m, sigma), 1e-8))
        # Tukey (c = 4.685 MADs) may drop a good window when the 40-point MAD comes out low
        assert cal.model == "start" and cal.observable and cal.n_windows >= m - 3
        eo.append((cal.offset - OFFSET) / K_DIAG)
        es.append(np.diag(cal.sensitivity) / K_DIAG - 1.0)
        assert np.count_nonzero(cal.sensitivity - np.diag(np.diag(cal.sensitivity))) == 0
    ratio_o = np.sqrt(np.mean(np.square(eo))) / (sigma * np.sqrt(3 / m))
    ratio_s = np.sqrt(np.mean(np.square(es))) / (sigma * np.sqrt(6 / m))
    assert 0.7 < ratio_o < 1.5 and 0.7 < ratio_s < 1.5, (ratio_o, ratio_s)


def test_ellipsoid_fit_rejects_a_few_non_static_windows():
    rng = np.random.default_rng(11)
    m, sigma = 40, 1e-3
    raw = _points(rng, m, sigma)
    raw[:4] += 0.15 * K_DIAG * _unit(rng.normal(size=(4, 3)))  # 150 mg of motion left in four windows
    cal = ellipsoid_fit(WindowSet.from_points(raw, 1e-8))
    assert cal.metadata["n_rejected"] >= 4
    # the 36 good windows give std sigma sqrt(3/36) ~ 0.3 mg on offsets: allow 5 of those
    np.testing.assert_allclose((cal.offset - OFFSET) / K_DIAG, 0, atol=5 * sigma * np.sqrt(3 / 36))
    np.testing.assert_allclose(np.diag(cal.sensitivity) / K_DIAG, 1, atol=5 * sigma * np.sqrt(6 / 36))
    # without robustness the same data are off by far more than that
    plain = np.linalg.lstsq(np.column_stack([raw ** 2, raw]), np.ones(m), rcond=None)[0]
    o_plain = -plain[3:] / (2 * plain[:3])
    assert np.max(np.abs((o_plain - OFFSET) / K_DIAG)) > 10 * sigma * np.sqrt(3 / 36)


def test_full_ellipsoid_fit_recovers_a_symmetric_sensitivity():
    rng = np.random.default_rng(12)
    K = np.array([[0.041, 0.0008, -0.0004], [0.0008, 0.039, 0.0006], [-0.0004, 0.0006, 0.043]])
    m, sigma = 60, 1e-3
    cal = ellipsoid_fit(WindowSet.from_points(_points(rng, m, sigma, K=K), 1e-8), full=True)
    np.testing.assert_allclose(cal.sensitivity, cal.sensitivity.T)
    # 9 parameters from 60 points: entry errors ~ sigma * s * sqrt(9/M); allow 5x
    tol = 5 * sigma * 0.04 * np.sqrt(9 / m)
    np.testing.assert_allclose(cal.sensitivity, K, atol=tol)
    np.testing.assert_allclose(cal.offset, OFFSET, atol=tol)
    assert cal.metadata["full"] is True


def test_ellipsoid_fit_refuses_bad_coverage():
    rng = np.random.default_rng(13)
    with pytest.raises(ValueError, match="at least 6"):
        ellipsoid_fit(WindowSet.from_points(_points(rng, 5, 1e-3), 1e-8))
    with pytest.raises(ValueError, match="at least 9"):
        ellipsoid_fit(WindowSet.from_points(_points(rng, 8, 1e-3), 1e-8), full=True)
    # one posture: 30 windows within ~3 degrees of "upright"
    a = _unit(np.array([0.0, 0.0, 1.0]) + 0.05 * rng.normal(size=(30, 3)))
    with pytest.raises(ValueError, match="orientation coverage insufficient"):
        ellipsoid_fit(WindowSet.from_points(a @ np.diag(K_DIAG) + OFFSET, 1e-8))
    # a 15-degree cap fits an ellipsoid exactly (no noise) but is refused by the cap check
    th = np.radians(15) * np.sqrt(rng.uniform(size=40))
    ph = rng.uniform(0, 2 * np.pi, 40)
    cap = np.column_stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])
    with pytest.raises(ValueError, match=r"all windows within 1[45]\.\d° of one direction"):
        ellipsoid_fit(WindowSet.from_points(cap @ np.diag(K_DIAG) + OFFSET, 1e-8))
    # pitch only (standing <-> lying on the back): y carries no gravity, only noise
    th = rng.uniform(-0.3, 1.8, 30)
    pitch = np.column_stack([np.sin(th), np.zeros(30), np.cos(th)]) + rng.normal(0, 1e-3, (30, 3))
    for full in (False, True):
        with pytest.raises(ValueError, match=r"orientation coverage insufficient: axis y \(0\.\d\d g\) never carries"):
            ellipsoid_fit(WindowSet.from_points(pitch @ np.diag(K_DIAG) + OFFSET, 1e-8), full=full)
    # rotation about z only: all windows in one plane, z never varies
    ph = rng.uniform(0, 2 * np.pi, 30)
    ring = np.column_stack([np.cos(ph), np.sin(ph), np.zeros(30)])
    with pytest.raises(ValueError, match="orientation coverage insufficient"):
        ellipsoid_fit(WindowSet.from_points(ring @ np.diag(K_DIAG) + OFFSET, 1e-8))


def _still_and_moving(rng, postures, still_s=6.0, move_s=2.0, fs=100.0):
    """Specific force [g]: still postures joined by 2 s shaking turns, noise NOISE_G."""
    parts = []
    nm = int(move_s * fs)
    for i, p in enumerate(postures):
        parts.append(np.repeat(p[None], int(still_s * fs), axis=0))
        if i + 1 < len(postures):
            s = np.linspace(0, 1, nm)[:, None]
            phase = 2 * np.pi * 1.5 * np.arange(nm)[:, None] / fs * np.array([1.0, 1.3, 0.7])
            parts.append(_unit((1 - s) * p + s * postures[i + 1]) + 0.3 * np.sin(phase))
    f = np.concatenate(parts)
    f = f + rng.normal(0, NOISE_G, f.shape)
    return np.arange(f.shape[0]) / fs, f


@pytest.mark.parametrize("units,scale,offset", [
    ("counts", np.array([4096.0, 4010.0, 4150.0]), np.array([32768.0, 32500.0, 33100.0])),
    ("m/s2", np.full(3, 9.80665), np.array([0.3, -0.2, 0.5])),
])
def test_bootstrap_recovers_scale_and_offset_in_unknown_units(units, scale, offset):
    rng = np.random.default_rng(21)
    t, f = _still_and_moving(rng, _unit(rng.normal(size=(14, 3))))
    raw = f * scale + offset
    raw[rng.choice(raw.shape[0], 5, replace=False), 0] = np.nan  # each may cut a still segment below 2 s
    cal = bootstrap(t, raw)
    assert cal.model == "start" and cal.observable
    assert cal.metadata["method"] == "bootstrap+ellipsoid_fit" and cal.metadata["n_still_windows"] >= 14 - 5
    # window means carry ~NOISE_G / sqrt(400) = 0.2 mg each; 14 windows give ~0.1 mg on the
    # offsets and ~0.2 % ... well under the 2 mg / 0.2 % asserted here (motion leakage margin)
    np.testing.assert_allclose((cal.offset - offset) / scale, 0, atol=2e-3)
    np.testing.assert_allclose(np.diag(cal.sensitivity) / scale, 1, atol=2e-3)
    # calibrated still data have norm 1 g
    a = cal.apply(raw[:300])
    np.testing.assert_allclose(np.nanmean(np.linalg.norm(a, axis=1)), 1.0, atol=2e-3)


def test_bootstrap_one_posture_gives_an_isotropic_scale_only():
    rng = np.random.default_rng(22)
    up = _unit(np.array([0.2, -0.1, 1.0]))
    t, f = _still_and_moving(rng, _unit(up + 0.03 * rng.normal(size=(8, 3))))  # 8 windows within ~3°
    raw = 9.80665 * f  # m/s², no offset: the median norm is g in these units
    cal = bootstrap(t, raw)
    assert not cal.observable and cal.model == "start"
    assert "isotropic scale" in cal.message and "orientation coverage insufficient" in cal.message
    np.testing.assert_allclose(cal.sensitivity, 9.80665 * np.eye(3), rtol=1e-3)
    np.testing.assert_array_equal(cal.offset, 0.0)


def test_bootstrap_refuses_data_without_information():
    t = np.arange(1000) / 100.0
    with pytest.raises(ValueError, match="constant"):
        bootstrap(t, np.ones((1000, 3)))
    with pytest.raises(ValueError, match=r"t \(N,\) and raw \(N, 3\)"):
        bootstrap(t, np.ones((1000, 2)))
    rng = np.random.default_rng(23)
    with pytest.raises(ValueError, match="do not stand out of the noise floor"):  # white noise: no gravity
        bootstrap(t, rng.normal(size=(1000, 3)))
    # still for 1 s, moving for 1 s, alternating: no still segment reaches min_duration_s (2 s).
    # (Motion of constant intensity throughout cannot be told from noise by a scale-free rule.)
    moving = (np.arange(1000) // 100) % 2 == 1
    shake = 0.3 * np.sin(2 * np.pi * 2.0 * t[:, None] * np.array([1.0, 1.3, 0.7]))
    f = np.array([0.0, 0.0, 1.0]) + rng.normal(0, NOISE_G, (1000, 3)) + moving[:, None] * shake
    with pytest.raises(ValueError, match="no still segment of at least 2.0 s"):
        bootstrap(t, f)


def _nees_stats(full, seeds=150):
    """NEES of the held covariance the ellipsoid fit attaches, over seeds of M = 40 / 60 window means."""
    m = 60 if full else 40
    nees = []
    for seed in range(seeds):
        rng = np.random.default_rng(1000 + seed)
        cal = ellipsoid_fit(WindowSet.from_points(_points(rng, m, 1e-3), 1e-8), full=full)
        held = cal.metadata["held_covariance"]
        idx = {"x": 0, "y": 1, "z": 2}
        est = [cal.sensitivity[idx[n[2]], idx[n[-1]]] if n[0] == "s" else cal.offset[idx[n[2]]] for n in held["names"]]
        tru = [np.diag(K_DIAG)[idx[n[2]], idx[n[-1]]] if n[0] == "s" else OFFSET[idx[n[2]]] for n in held["names"]]
        e = np.subtract(est, tru)
        nees.append(e @ np.linalg.solve(np.asarray(held["cov"]), e))
    return held["names"], np.asarray(nees), m


@pytest.mark.parametrize("full", [False, True])
def test_ellipsoid_fit_held_covariance_matches_its_error(full):
    names, nees, m = _nees_stats(full)
    p = len(names)
    assert names[:3] == ["s_x", "s_y", "s_z"] and names[-3:] == ["o_x", "o_y", "o_z"] and p == (9 if full else 6)
    # With the residual variance estimated on nu = M - P dof the NEES is Hotelling-like, mean
    # P nu / (nu - 2) (6.4 / 9.4), not P. Tolerance: 4 standard errors of the mean over the seeds,
    # the SE from the sample NEES spread itself (heavier-tailed than chi²: random designs, robust weights).
    nu = m - p
    expected = p * nu / (nu - 2)
    se = nees.std(ddof=1) / np.sqrt(nees.size)
    assert abs(nees.mean() - expected) < 4 * se, (nees.mean(), expected, se)
    # and the spread is not a bare chi² with half the variance: >= 85 % inside the chi²_P 95 % point
    from scipy.stats import chi2
    assert np.mean(nees < chi2.ppf(0.95, p)) > 0.85


def test_bootstrap_isotropic_fallback_states_held_sensitivity_uncertainty_for_offsets_only():
    from gravcal.core.estimators.lotters import LottersBatch
    from gravcal.core.estimators.consider import HELD_KEY, CONSIDER_KEY
    rng = np.random.default_rng(31)
    up = _unit(np.array([0.1, -0.05, 1.0]))
    t, f = _still_and_moving(rng, _unit(up + 0.03 * rng.normal(size=(8, 3))))
    start = bootstrap(t, 9.80665 * f)
    assert not start.observable and "only assumed equal" in start.message
    held = start.metadata[HELD_KEY]
    assert held["names"] == ["s_x", "s_y", "s_z"]
    scale = start.sensitivity[0, 0]
    np.testing.assert_allclose(np.sqrt(np.diag(held["cov"])) / scale, 0.20, rtol=1e-12)

    # Offsets-only fits from that start: upright-only windows (within ~5°), true per-axis gains unequal
    # by 3 % (1 sigma), true offsets 20 mg. The held 20 % is a conservative bound, not the truth's
    # spread, so the NEES (3 dof) must not exceed chi² (mean <= 3 + 4 SE, SE = sqrt(6 / N)); without
    # the consider term (window noise only) the offset error (z: confounded with s_z) is far outside.
    with_c, without = [], []
    n_seeds = 100
    for seed in range(n_seeds):
        r = np.random.default_rng(2000 + seed)
        s_true = scale * (1 + 0.03 * r.normal(size=3))
        o_true = scale * 0.02 * r.normal(size=3)
        a = _unit(np.array([0.0, 0.0, 1.0]) + 0.05 * r.normal(size=(30, 3)))
        raw = (a + r.normal(0, 2e-4, (30, 3))) * s_true + o_true
        cal = LottersBatch("offsets").fit(WindowSet.from_points(raw, (2e-4 * scale) ** 2), start=start)
        e = cal.offset - o_true
        with_c.append(e @ np.linalg.solve(cal.covariance, e))
        c_noise = np.asarray(cal.metadata[CONSIDER_KEY]["covariance_noise_only"])
        without.append(e @ np.linalg.solve(c_noise, e))
    with_c, without = np.asarray(with_c), np.asarray(without)
    assert with_c.mean() < 3 + 4 * np.sqrt(6 / n_seeds), with_c.mean()
    assert np.mean(with_c < 11.34) > 0.97  # chi²_3 99 % point
    assert np.median(without) > 100, np.median(without)


def test_bootstrap_noise_floor_is_the_percentile_of_the_moving_std_whatever_the_probe_threshold():
    # the probe runs with a vanishing threshold (no still windows to build): its detection signal, the max
    # per-axis moving std, is the one a probe that finds everything still gives (the oracle here)
    from gravcal.core.detectors.variance import MovingVarianceDetector
    from gravcal.core.estimators.start import _noise_floor

    rng = np.random.default_rng(5)
    t, f = _still_and_moving(rng, _unit(rng.normal(size=(8, 3))))
    raw = f * 4096.0 + 32768.0
    raw[rng.choice(raw.shape[0], 3, replace=False), 1] = np.nan
    probe = MovingVarianceDetector(100.0, window_s=0.25, threshold_g=1e9, max_duration_s=None)
    found = probe.update(t, raw)
    det = probe.last_detection
    assert len(found + probe.flush()) >= 3  # still everywhere but around the NaN rows
    det = det[np.isfinite(det) & (np.arange(det.shape[0]) >= probe.w - 1)]
    assert _noise_floor(t, raw, 100.0, 0.25, 2.0) == max(float(np.percentile(det, 2.0)), 0.5 * float(
        np.nanmin(np.where(np.abs(np.diff(raw, axis=0)) > 0, np.abs(np.diff(raw, axis=0)), np.inf))))


@pytest.mark.parametrize("chunk", [7, 100, 1000, 1 << 13])
def test_noise_floor_in_pieces_equals_the_whole_segment_at_once(monkeypatch, chunk):
    # the probe fed piece by piece gives the whole-segment detection signal and quantum bit for bit,
    # also when the smallest step lies across two pieces (only the step into a piece sees it)
    from gravcal.core.detectors.variance import MovingVarianceDetector
    from gravcal.core.estimators import start

    rng = np.random.default_rng(11)
    t, f = _still_and_moving(rng, _unit(rng.normal(size=(8, 3))))
    raw = np.round(f * 8.0) * 2.0 + 32768.0  # coarse: still rows constant, floor = half the quantum; steps of 2 ...
    b = (raw.shape[0] // 2) // chunk * chunk  # ... but for one of 1 count, across a piece boundary
    if b:
        raw[b:, 0] += raw[b - 1, 0] + 1.0 - raw[b, 0]
    raw[rng.choice(raw.shape[0], 5, replace=False), 1] = np.nan

    probe = MovingVarianceDetector(100.0, window_s=0.25, threshold_g=np.finfo(float).tiny, max_duration_s=None)
    probe.update(t, raw)
    det = probe.last_detection
    det = det[np.isfinite(det) & (np.arange(det.shape[0]) >= probe.w - 1)]
    steps = np.abs(np.diff(raw, axis=0))
    quantum = float(steps[np.isfinite(steps) & (steps > 0)].min())
    expected = max(float(np.percentile(det, 2.0)), 0.5 * quantum)

    monkeypatch.setattr(start, "FLOOR_CHUNK", chunk)
    floor = start._noise_floor(t, raw, 100.0, 0.25, 2.0)
    assert floor == expected
    if chunk < raw.shape[0] // 2:
        assert quantum == 1.0 and floor == 0.5


def test_an_exact_fit_states_the_equal_gain_uncertainty_not_its_own():
    """Six windows for six unknowns leave no residual: the linearised covariance would be ~0 whatever the
    error (a one-pose chamber's six handling moments: gains 15 % off, stated to 0.04 %). The fit is kept as
    a start, held at ±20 % per gain like the equal-gain start; with 3 windows more its own covariance."""
    from gravcal.core.estimators.start import ISOTROPIC_SENS_REL_STD

    rng = np.random.default_rng(31)

    def held_rel(m):
        cal = ellipsoid_fit(WindowSet.from_points(_points(rng, m, 1e-3), 1e-8))
        held = cal.metadata["held_covariance"]
        sd = np.sqrt(np.diag(np.asarray(held["cov"])))
        return np.array([sd[held["names"].index(f"s_{a}")] for a in "xyz"]) / np.abs(np.diag(cal.sensitivity)), held

    rel, held = held_rel(6)
    np.testing.assert_allclose(rel, ISOTROPIC_SENS_REL_STD)
    assert "no residual" in held["source"]
    rel, held = held_rel(40)
    assert np.all(rel < 0.01) and "linearised LS covariance" in held["source"]
