"""Issue 7's bad input, end to end through the calibrators: no rotations between windows,
rotations beyond the gyro's range (saturation), a step height of zero, unknown or one the data
cannot match. Each gives a message naming the problem and no estimate (no sensitivity, no
pair used, a null rate), never a silent wrong one.

(The building blocks' messages are tested in tests/core/test_gyro.py: a single saturated / quiet /
about-gravity pair, calibrate_gyro on one pose, step heights 0, None, NaN, negative.)
"""
import numpy as np
import pytest

from gravcal.core.calibration import Calibration
from gravcal.core.detectors import QuasiStaticDetector, detect
from gravcal.core.gyro import OnlineGyroCalibrator, calibrate_gyro
from gravcal.core.gyro.footmotion import foot_poses, simulate_foot, stair_climb
from gravcal.core.gyro.pose import NO_ROTATION, SATURATED
from gravcal.core.gyro.scapellato import placements, step_height_search
from gravcal.core.samples import raw_triad
from gravcal.core.simulate import simulate

FS = 100.0
NOMINAL = 357.36  # counts per rad/s, the daemon's start without a [gyro] configuration
RANGE = np.radians(300.0)
NOMINAL_MV_PER_DPS = 0.67


def online(gyro, t, raw, acc, block=50):
    det = QuasiStaticDetector(FS, to_g=acc)
    cal = OnlineGyroCalibrator(FS, k=1, axis=(0.0, 1.0, 0.0), hp_hz=0.3, start_sensitivity=NOMINAL,
                               range_rad_s=RANGE, rails=(0, 4095))
    for i in range(0, gyro.shape[0], block):
        cal.push(gyro[i:i + block])
        for w in det.update(t[i:i + block], raw[i:i + block]):
            cal.window(w, acc)
    return cal


def assert_declined(cal, reason):
    assert cal.sensitivity is None and not cal.observable and cal.n_pairs == 0, cal.message
    assert cal.message.startswith("no sensitivity:") and reason in cal.message, cal.message
    d = cal.to_json_dict()
    assert d["sensitivity"] is None and d["observable"] is False and d["rejected_pairs"].get(reason, 0) >= 1


def fast_pose_session(seed, scale):
    """Foot pitch changes of 60-90° in 0.22-0.28 s (peaks 400-600 °/s) on a board whose
    ENC-03J scale factor is ``scale`` x nominal: every pose change clips at the sensor's ±300 °/s."""
    motion = foot_poses(np.random.default_rng(seed), n_poses=10, hold_s=(4.0, 8.0), move_s=(0.22, 0.28),
                        pitch_range_deg=(-45.0, 45.0), min_change_deg=60.0)
    s = simulate_foot(motion, seed, gyro_sensor={"scale_mv_per_dps": NOMINAL_MV_PER_DPS * scale})
    assert np.abs(motion.omega[:, 1]).max() > RANGE * 1.3  # the motion does exceed the range
    return s


@pytest.mark.parametrize("scale", [0.8, 1.2])  # the ENC-03J's ±20 % spread around the start scale
def test_rotations_beyond_the_range_are_refused_and_none_is_used(scale):
    """A board 20 % below nominal reads its 300 °/s limit as 240 °/s at the start scale: the
    saturation test allows for the scale's uncertainty, so not even the first clipped pair
    gets in (it would pull the scale up, online for good)."""
    s = fast_pose_session(3, scale)
    ws = detect(s.t, s.acc_raw, fs=FS, to_g=s.acc_calibration)
    off = calibrate_gyro(s.t, s.gyro, ws, s.acc_calibration, fs=FS, hp_hz=0.3, axis=(0.0, 1.0, 0.0),
                         range_rad_s=RANGE, rails=(0, 4095), start=NOMINAL, folds=0)
    assert_declined(off, SATURATED)
    on = online(s.gyro, s.t, s.acc_raw, s.acc_calibration)
    cal = on.calibration
    assert_declined(cal, SATURATED)
    assert cal.n_windows >= 4 and cal.rejected_pairs == {SATURATED: cal.n_windows - 1}  # every bracketed change
    assert np.isnan(on.rate(s.gyro[:100])).all()  # no rate with a made-up scale
    assert abs(cal.bias[0] - s.truth["bias_counts"]) < 5 * cal.bias_std[0]  # the bias still comes


def test_a_still_session_gives_a_bias_and_says_there_was_no_rotation():
    sim = simulate("static", seed=4, duration=200.0, fs=FS)  # windows cut at 60 s
    smp = sim.samples
    acc = Calibration.from_dict(sim.truth["calibration"])
    on = online(smp["gyro"].astype(float), smp["t"].astype(float), raw_triad(smp), acc)
    cal = on.calibration
    assert cal.n_windows >= 2, "the still session gives windows (a bias)"
    assert cal.sensitivity is None and not cal.observable and cal.n_pairs == 0
    assert "no usable rotation between quasi-static windows" in cal.message, cal.message
    assert cal.rejected_pairs.get(NO_ROTATION, 0) >= 1, cal.rejected_pairs
    assert np.isfinite(cal.bias[0]) and np.isnan(on.rate(smp["gyro"][:10].astype(float))).all()


def test_a_step_height_the_climb_cannot_match_gives_no_estimate():
    """Told 40 cm for 17 cm steps: no sensitivity within [0.5, 2] x start makes the strapdown
    heights match (4-5 mm per 10 % of scale), so the search ends at its interval's edge and
    says so, instead of returning the edge as an estimate. 0, None, NaN: tests/core/test_gyro.py."""
    sc = stair_climb(np.random.default_rng(2000), n_steps=6, step_height_m=0.17)
    s = simulate_foot(sc.motion, 0)
    pl = placements(s.gyro, s.acc_raw, s.acc_calibration, sc.stances, bias=s.truth["bias_counts"], fs=FS,
                    hp_hz=s.truth["hp_hz"], acc_lowpass_hz=s.model["analog_lowpass"].f3db_hz[:3])
    assert abs(step_height_search(pl, 0.17, start=NOMINAL).sensitivity
               / s.truth["sensitivity_counts_per_rad_s"] - 1) < 0.03  # the right height works
    with pytest.raises(ValueError, match="ended at the edge"):
        step_height_search(pl, 0.40, start=NOMINAL)
    with pytest.raises(ValueError, match="step height unknown"):
        step_height_search(pl, None, start=NOMINAL)
