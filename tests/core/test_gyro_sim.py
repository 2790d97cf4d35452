"""Gyro calibration on simulated sessions with known bias and sensitivity (datasheet spreads:
the ENC-03J scale factor is drawn within +-20 %, so every seed has its own sensitivity error
against the nominal 0.67 mV/(°/s)).

Tolerances: each method reports a standard deviation; over n seeds the z-scores
(estimate - truth) / std must all lie within 3.5 (for ~16-36 draws of a unit normal the chance
of any beyond 3.5 is < 2 %) and their mean square within the 99.9 % point of chi2(n)/n. The
step-height search has a known systematic part (documented in docs/gyro.md: +0.7 % from the
ADXL210 duty-cycle timing and 100 Hz sampling), allowed for as 1.5 % on top of 3 sigma.
"""
import numpy as np
import pytest
from scipy import stats

from gravcal.core.calibration import Calibration
from gravcal.core.detectors import QuasiStaticDetector, detect
from gravcal.core.gyro import OnlineGyroCalibrator, calibrate_gyro
from gravcal.core.gyro.footmotion import foot_poses, simulate_foot, stair_climb
from gravcal.core.gyro.pose import SATURATED
from gravcal.core.gyro.scapellato import placements, step_height_search
from gravcal.core.samples import raw_triad
from gravcal.core.simulate import simulate
from seed_pool import pmap

FS = 100.0
NOMINAL = 357.36  # counts per rad/s: 0.67 mV/(°/s) x 7.5 x 4096 / 3.3 V


def chi2_limit(n: int) -> float:
    return stats.chi2.ppf(0.999, n) / n


def foot_session(seed, **kw):
    s = simulate_foot(foot_poses(np.random.default_rng(1000 + seed), **kw), seed)
    ws = detect(s.t, s.acc_raw, fs=FS, to_g=s.acc_calibration)
    return s, ws


def enc03j_calibration(s, ws, **kw):
    tr = s.truth
    return calibrate_gyro(s.t, s.gyro, ws, s.acc_calibration, fs=FS, hp_hz=tr["hp_hz"], axis=tr["axis"],
                          range_rad_s=tr["range_rad_s"], rails=(0, 4095), folds=0, **kw)


def foot_calibration(seed: int):
    """(calibration, truth) of a 20-pose foot session (computed in a worker process)."""
    s, ws = foot_session(seed, n_poses=20)
    return enc03j_calibration(s, ws), s.truth


def triaxial_calibration(seed: int):
    """(calibration, true sensitivity matrix, true bias) of a DC-coupled triaxial gyro on a Lötters session
    (computed in a worker process)."""
    rng = np.random.default_rng(50 + seed)
    sim = simulate("loetters", seed=seed, duration=300.0, theta_max_deg=120)
    acc = Calibration.from_dict(sim.truth["calibration"])
    S = np.diag(rng.uniform(0.8, 1.2, 3)) * 6000 + rng.normal(0, 60, (3, 3))
    b = 32768 + rng.normal(0, 50, 3)
    gyro = sim.motion.omega @ S.T + b + rng.normal(0, 3, (len(sim.motion), 3))
    ws = detect(sim.samples["t"], raw_triad(sim.samples), fs=FS, to_g=acc)
    return calibrate_gyro(sim.samples["t"], gyro, ws, acc, fs=FS, folds=0), S, b


@pytest.mark.slow
def test_pose_to_pose_recovers_enc03j_bias_and_sensitivity_within_uncertainty():
    z = []
    for cal, truth in pmap(foot_calibration, [(seed,) for seed in range(8)]):
        assert cal.observable and cal.sensitivity is not None, cal.message
        z.append((cal.sensitivity[0, 0] - truth["sensitivity_counts_per_rad_s"]) / cal.std["S"])
        z.append((cal.bias[0] - truth["bias_counts"]) / cal.bias_std[0])
        assert cal.methods["sensitivity"].startswith("pose-to-pose")
    z = np.array(z)
    assert np.all(np.abs(z) < 3.5), z
    assert np.mean(z**2) < chi2_limit(z.size), z


@pytest.mark.slow
def test_pose_to_pose_recovers_a_triaxial_gyro_matrix_within_uncertainty():
    """Lötters-style postures (random rotation axes) with a DC-coupled triaxial gyro whose
    3x3 sensitivity has +-20 % scale errors and ~1 % cross-axis terms."""
    z = []
    for cal, S, b in pmap(triaxial_calibration, [(seed,) for seed in range(3)]):
        assert cal.observable, cal.message
        sd = np.sqrt(np.diag(cal.sensitivity_cov)).reshape(3, 3)
        z += list(((cal.sensitivity - S) / sd).ravel()) + list((cal.bias - b) / cal.bias_std)
    z = np.array(z)
    assert np.all(np.abs(z) < 3.5), z
    assert np.mean(z**2) < chi2_limit(z.size), z


@pytest.mark.slow
def test_step_climbing_search_recovers_the_sensitivity_from_a_staircase():
    rel = []
    for seed in range(4):
        sc = stair_climb(np.random.default_rng(2000 + seed), n_steps=10, step_height_m=0.17)
        s = simulate_foot(sc.motion, seed)
        S = s.truth["sensitivity_counts_per_rad_s"]
        pl = placements(s.gyro, s.acc_raw, s.acc_calibration, sc.stances, bias=s.truth["bias_counts"], fs=FS,
                        hp_hz=s.truth["hp_hz"], acc_lowpass_hz=s.model["analog_lowpass"].f3db_hz[:3])
        res = step_height_search(pl, 0.17, start=NOMINAL)
        assert abs(res.sensitivity - S) < 3 * res.std + 0.015 * S, (res.sensitivity, S, res.std)
        assert res.rms_error_m < 2e-3  # heights within 2 mm once the sensitivity fits
        rel.append(res.sensitivity / S - 1)
    assert abs(np.mean(rel)) < 0.015
    # a wrong step height moves the estimate: the search does use the height
    res_wrong = step_height_search(pl, 0.17 * 1.03, start=NOMINAL)
    assert abs(res_wrong.sensitivity / S - 1) > 0.05


def test_fast_pose_changes_beyond_the_range_are_rejected_as_saturated():
    s, ws = foot_session(3, n_poses=10, move_s=(0.2, 0.25), pitch_range_deg=(-60.0, 60.0))
    assert np.max(np.abs(s.motion.omega[:, 1])) > np.deg2rad(300)  # the motion exceeds the ENC-03J range
    cal = enc03j_calibration(s, ws, start=NOMINAL)
    assert cal.rejected_pairs.get(SATURATED, 0) >= 1
    assert SATURATED in cal.message or cal.sensitivity is None


def test_online_calibrator_streams_to_the_offline_result():
    s, ws = foot_session(11, n_poses=20)
    tr = s.truth
    det = QuasiStaticDetector(FS, to_g=s.acc_calibration)
    online = OnlineGyroCalibrator(FS, k=1, axis=tr["axis"], hp_hz=tr["hp_hz"], start_sensitivity=NOMINAL,
                                  range_rad_s=tr["range_rad_s"], rails=(0, 4095))
    for i in range(0, s.t.size, 256):  # the daemon's block loop
        online.push(s.gyro[i:i + 256])
        for w in det.update(s.t[i:i + 256], s.acc_raw[i:i + 256]):
            online.window(w, s.acc_calibration)
    cal = online.calibration
    assert cal.observable, cal.message
    S = tr["sensitivity_counts_per_rad_s"]
    assert abs(cal.sensitivity[0, 0] - S) < 3.5 * cal.std["S"]
    assert abs(cal.bias[0] - tr["bias_counts"]) < 3.5 * cal.bias_std[0]
    offline = enc03j_calibration(s, ws)
    assert abs(cal.sensitivity[0, 0] - offline.sensitivity[0, 0]) < 2 * cal.std["S"]
    rate = online.rate(s.gyro[:500])
    assert rate.shape == (500, 1) and np.all(np.isfinite(rate))


def test_bias_is_the_conditioning_reference_not_the_sensor_null():
    """Two boards whose ENC-03J null voltages differ by 0.3 V, drifting 5 mV/°C during a fast
    20 °C warm-up: the high-pass removes the null itself, so the bias at the ADC is the stage's
    reference vref_ratio * 2^12 - 1/2 counts (ADC floor) for both boards, plus what a first-order
    high-pass passes of a ramp: gain * tau * dV_null/dt (here 5.9 counts; 0.02 counts for the
    assumed 0.5 mV/°C and a 10 °C warm-up over 20 min)."""
    m = foot_poses(np.random.default_rng(4), n_poses=8)
    m.temp = np.linspace(20.0, 40.0, len(m))
    dT_dt = 20.0 / (m.t[-1] - m.t[0])  # °C/s
    for null_v in (1.2, 1.5):
        s = simulate_foot(m, 4, gyro_sensor={"null_v": null_v, "null_tempco_mv_per_c": 5.0})
        cond = s.model["gyro_conditioning"].params
        tau = 1.0 / (2 * np.pi * float(cond["hp_hz"]))
        ramp_counts = float(cond["gain"]) * tau * 5e-3 * dT_dt / 3.3 * 4096
        ws = detect(s.t, s.acc_raw, fs=FS, to_g=s.acc_calibration)
        cal = enc03j_calibration(s, ws, start=NOMINAL)
        assert s.truth["bias_counts"] == 2047.5
        assert abs(cal.bias[0] - (2047.5 + ramp_counts)) < 3.5 * cal.bias_std[0], (cal.bias, ramp_counts)
        assert cal.bias_std[0] < 0.5
