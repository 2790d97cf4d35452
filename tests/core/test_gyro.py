"""Gyro building blocks: the board's high-pass and its inverse, attitude integration, the
pose-to-pose Jacobian, window bias, the stillness gate, and the bad-input messages."""
import numpy as np
import pytest
from scipy import signal
from scipy.spatial.transform import Rotation

from gravcal.core.calibration import Calibration
from gravcal.core.gyro import (GyroBiasEstimator, GyroCalibration, GyroStillnessGate, HighPassInverse, PoseToPose,
                               calibrate_gyro, reconstruct, window_bias)
from gravcal.core.gyro.conditioning import highpass_ba
from gravcal.core.gyro.pose import ABOUT_GRAVITY, NO_ROTATION, SATURATED, Pair
from gravcal.core.gyro.rotation import attitude
from gravcal.core.gyro.scapellato import Placement, step_height_search
from gravcal.core.model.defaults import default_model
from gravcal.core.model.enc03j import conditioning_response, gyro_truth
from gravcal.core.windows import WindowSet

from filter_bounds import first_order_design_bound

FS = 100.0


def test_conditioning_gain_and_phase_at_gait_frequencies_follow_the_two_first_order_sections():
    model = default_model(nominal=True)
    f = np.array([0.5, 1.0, 2.0])
    gain, phase = conditioning_response(model, f, FS)
    # first-order HP (0.3 Hz) x LP (25 Hz), bilinear with pre-warped corners: the analog response
    # at warped frequencies (tan(pi f / fs) / tan(pi f_c / fs))
    def ratio(fc):
        return np.tan(np.pi * f / FS) / np.tan(np.pi * fc / FS)
    hp = 1j * ratio(0.3) / (1 + 1j * ratio(0.3))
    lp = 1 / (1 + 1j * ratio(25.0))
    assert np.allclose(gain, np.abs(hp * lp), rtol=1e-9)
    assert np.allclose(phase, np.degrees(np.angle(hp * lp)), atol=1e-7)
    assert gain[0] < 0.9 and phase[0] > 25  # the gait band is not flat: 0.5 Hz loses 14 % and leads 30°


def test_highpass_inverse_recovers_the_rate_exactly_and_streams_block_split():
    rng = np.random.default_rng(3)
    x = np.convolve(rng.normal(size=3000), np.hanning(40), "same")
    x[:200] = 0.0  # starts at rest
    x[-1000:] = 0.0  # and ends at rest (10 s = 19 tau)
    b, a = highpass_ba(0.3, FS)
    y = signal.lfilter(b, a, x)
    assert abs(y.sum()) < 1e-6 * np.abs(x).sum()  # zero DC gain: the integral is gone
    whole = reconstruct(y, 0.3, FS)
    assert np.max(np.abs(whole - x)) < 1e-9 * np.max(np.abs(x))
    inv = HighPassInverse(0.3, FS)
    parts = np.concatenate([inv.update(y[i:i + 77]) for i in range(0, y.size, 77)])
    assert np.array_equal(parts, whole)


@pytest.mark.parametrize("hp_hz,fs", [(0.3, 100.0), (0.3, 200.0), (0.05, 50.0), (1.7, 100.0)])
def test_inverse_inverts_the_simulators_own_high_pass(hp_hz, fs):
    """The inverse's (b, a) is the simulated board's high-pass section bit for bit (one design), and SciPy's
    design to the rounding of the operations both take (tests/core/filter_bounds.py)."""
    b, a = highpass_ba(hp_hz, fs)
    sos = default_model(nominal=True)["gyro_conditioning"].__class__(hp_hz=hp_hz).sos(fs)[0]
    assert np.array_equal(b, sos[:2]) and np.array_equal(a, sos[3:5])
    b_ref, a_ref = signal.butter(1, hp_hz, "highpass", fs=fs)
    rel_k, _, rel_pole = first_order_design_bound(hp_hz, fs)
    assert np.all(np.abs(b - b_ref) <= rel_k * np.abs(b_ref)) and a[0] == a_ref[0] == 1.0
    assert abs(a[1] - a_ref[1]) <= rel_pole * abs(a_ref[1])


def test_attitude_scan_equals_the_sequential_product():
    rng = np.random.default_rng(0)
    w = rng.normal(size=(513, 3))
    r = Rotation.identity()
    for k in range(w.shape[0]):
        r = r * Rotation.from_rotvec(w[k] * 0.01)
    assert np.max(np.abs(attitude(w, 0.01)[-1] - r.as_matrix())) < 1e-12


def _pair(u, g_i, g_j=None, n=40):
    z = np.zeros((n,) + u.shape[1:])
    return Pair(u=np.concatenate([z, u, z]), dt=0.01, g_i=g_i, g_j=g_i if g_j is None else g_j,
                cov_i=np.eye(3) * 1e-8, cov_j=np.eye(3) * 1e-8, rest_rms=np.ones(u.shape[1]), n_rest=2 * n,
                n_i=n, n_j=n)


@pytest.mark.parametrize("kind", ["scalar", "matrix"])
def test_pose_jacobian_matches_finite_differences(kind):
    rng = np.random.default_rng(1)
    u = np.cumsum(rng.normal(size=(300, 3 if kind == "matrix" else 1)), axis=0) * 3
    g = rng.normal(size=3)
    g /= np.linalg.norm(g)
    start = np.eye(3) * 0.01 + rng.normal(size=(3, 3)) * 1e-3 if kind == "matrix" else np.array([0.01])
    est = PoseToPose(kind, start, axis=[0.0, 1.0, 0.0])
    p = _pair(u, g)
    g0, J, _, _ = est._predict(est.x, p)
    num = np.zeros_like(J)
    for i in range(est.x.size):
        x = est.x.copy()
        x[i] += 1e-7
        num[:, i] = (est._predict(x, p)[0] - g0) / 1e-7
    assert np.max(np.abs(J - num)) < 2e-3 * np.max(np.abs(J))  # first order in the within-window motion


def test_window_bias_fits_the_highpass_tail_and_its_uncertainty_covers_the_error():
    """300 windows of tail + white noise: the bias z-scores have unit spread (within 20 %: the
    std of a std estimated from 300 draws is ~4 %, the mean of 300 z-scores ~0.06) and the
    plain mean would be biased."""
    b, a = highpass_ba(0.3, FS)
    q = -a[1]
    z, naive = [], []
    for seed in range(300):
        rng = np.random.default_rng(seed)
        n = 250
        y = 2047.5 + 40.0 * q ** np.arange(n) + rng.normal(0, 0.8, n)
        wb = window_bias(y, FS, 0.3)
        z.append((wb.bias[0] - 2047.5) / np.sqrt(wb.var[0]))
        naive.append(y.mean() - 2047.5)
    assert abs(np.std(z) - 1) < 0.2 and abs(np.mean(z)) < 0.2
    assert np.mean(naive) > 5.0  # the tail (40 counts, tau 0.53 s) biases a plain mean by ~8 counts


def test_recursive_bias_rejects_a_moving_window_after_a_robust_start():
    est = GyroBiasEstimator(k=1)
    rng = np.random.default_rng(0)
    for i in range(6):
        y = 100.0 + rng.normal(0, 1.0, 400)
        if i == 0:
            y += 25.0  # the first window holds a slow rotation: must not become the reference
        est.update(window_bias(y, FS), float(i))
    assert abs(est.bias[0] - 100.0) < 4 * est.std[0]
    assert est.bias[0] < 101.0  # median start: the outlier (+25) cannot dominate
    accepted = est.update(window_bias(130.0 + rng.normal(0, 1.0, 400), FS), 10.0)
    assert not accepted and est.n_rejected >= 1


def test_stillness_gate_confirms_rest_and_rejects_rotation():
    rng = np.random.default_rng(2)
    t = np.arange(300) / FS
    scale = gyro_truth(default_model(nominal=True))["sensitivity_counts_per_rad_s"]
    gate = GyroStillnessGate(FS, scale, hp_hz=0.3)
    still = 2047.5 + rng.normal(0, 0.8, t.size)
    ok, rms = gate.confirm(still)
    assert ok and rms < 0.01
    moving = still + scale * 0.3 * np.sin(2 * np.pi * 1.0 * t)  # 0.3 rad/s at 1 Hz (17 °/s)
    ok, rms = gate.confirm(moving)
    assert not ok and abs(rms - 0.3 / np.sqrt(2)) < 0.02


def test_pair_rejections_name_the_reason():
    est = PoseToPose("matrix", np.eye(3) / 100.0, range_rad_s=np.deg2rad(300))
    g = np.array([0.0, 0.0, 1.0])
    quiet = _pair(np.zeros((200, 3)), g)
    assert est.update(quiet).reason == NO_ROTATION
    turn_z = np.zeros((200, 3))
    turn_z[:, 2] = 100.0 * np.pi / 2 / 2.0  # 90° about z in 2 s, with gravity along z
    assert est.update(_pair(turn_z, g)).reason == ABOUT_GRAVITY
    fast = np.zeros((200, 3))
    fast[:, 0] = 100.0 * np.deg2rad(400)  # 400 °/s > 300 °/s range
    assert est.update(_pair(fast, g)).reason == SATURATED
    assert est.n_pairs == 0 and not est.observable
    assert "no usable rotation" in est.message() and "about the gravity axis" in est.message()


def test_calibrate_gyro_claims_no_sensitivity_without_rotations_and_says_why():
    """A recording whose windows all share one pose: bias yes, sensitivity no."""
    rng = np.random.default_rng(5)
    n = 4000
    gyro = 2047.5 + rng.normal(0, 0.8, n)
    acc = Calibration.nominal(np.zeros(3), 1.0)
    starts = np.arange(0, n - 400, 500)
    ws = WindowSet(np.tile([0.0, 0.0, 1.0], (starts.size, 1)), np.tile(np.eye(3) * 1e-6, (starts.size, 1, 1)),
                   np.full(starts.size, 300.0), (starts + 150) / FS, np.zeros((starts.size, 0)), starts, starts + 300)
    cal = calibrate_gyro(np.arange(n) / FS, gyro, ws, acc, fs=FS, hp_hz=0.3, start=357.0)
    assert cal.sensitivity is None and not cal.observable
    assert "no sensitivity" in cal.message and "no rotation between windows" in cal.message
    assert abs(cal.bias[0] - 2047.5) < 4 * cal.bias_std[0]
    with pytest.raises(ValueError, match="not determined"):
        cal.rate(gyro[:10])
    d = cal.to_json_dict()
    assert d["sensitivity"] is None and d["observable"] is False
    with pytest.raises(ValueError, match="no quasi-static windows"):
        calibrate_gyro(np.arange(n) / FS, gyro, ws.subset(np.array([], int)), acc, fs=FS)


@pytest.mark.parametrize("height, match", [(0.0, "must be positive"), (None, "step height unknown"),
                                           (float("nan"), "step height unknown"), (-0.17, "must be positive")])
def test_step_search_refuses_a_zero_or_unknown_height(height, match):
    p = Placement(u=np.zeros(50), f=np.tile([0.0, 0.0, 1.0], (50, 1)), n_stance=10, swing=slice(9, 40), dt=0.01)
    with pytest.raises(ValueError, match=match):
        step_height_search([p, p], height, start=357.0)


def test_gyro_calibration_rate_follows_the_convention():
    S = np.array([[50.0, 1.0, 0.0], [0.0, 60.0, 2.0], [0.5, 0.0, 55.0]])
    b = np.array([1.0, -2.0, 3.0])
    cal = GyroCalibration(bias=b, bias_std=np.zeros(3), sensitivity=S, sensitivity_cov=np.eye(9))
    w = np.array([[0.1, -0.2, 0.3]])
    assert np.allclose(cal.rate(S @ w[0] + b), w)
    d = cal.to_json_dict()
    assert d["units"]["convention"] == "omega = sensitivity^-1 (raw - bias)"
    assert np.allclose(d["sensitivity"], S) and set(d["std"]) == {"b_x", "b_y", "b_z"} | {
        f"S_{r}{c}" for r in "xyz" for c in "xyz"}
