"""End to end: `gravcald --emulate` publishes the calibrated gyro rate [rad/s] and reports the
gyro calibration in ?CALIB (issue 7; core.gyro.OnlineGyroCalibrator wired in the Processor).

Two daemon runs on the emulated serial bus, seed 0, at 50x:

- ``sagittal_postures`` (core/scenarios.py): a trunk-worn logger, board y medio-lateral, through
  sitting, bending, kneeling, lying down and getting up: pitch rotations about the ENC-03J's
  sensitive axis between still postures. The daemon must determine the sensitivity online
  (measured in-process for seeds 0-3: accelerometer accepted at 160-460 s of sensor time,
  gyro sensitivity ~40-60 s later from ~20 pairs, within 0.2 % and 0.8 sigma of the truth).
- ``six_position``: the board turned by hand between its faces, every turn about a different
  axis, none about y alone: the estimator must decline (no sensitivity, the reason in the
  message, null published rate), never claim a made-up scale.

Without a [gyro] configuration the daemon starts with no gyro calibration: IMU ``gyro`` is null.
Once the accelerometer calibration is accepted the quasi-static windows give the gyro bias;
pose-to-pose pairs give the sensitivity.

Truth: the emulator's sensor is ``default_model`` drawn from the seed's model stream (as
``daemon/emulation.emulated_truth``); ``core.model.enc03j.gyro_truth`` gives its bias (the conditioning
stage's reference level, 2047.5 counts) and pass-band sensitivity at the supply voltage, which
the test takes from the IMU ``vsupply`` field (the count scale goes as 1/Vsupply). The true
rate of every published sample is the scenario's body rate (re-planned from the seed's motion
stream, as the emulator plans it) along the gyro axis, through the model's conditioning filter
(0.3 Hz high-pass, 25 Hz low-pass): what the board's rate output carries, which the daemon
publishes as ``omega = (raw - bias) / sensitivity`` (docs/gyro.md §1).

Tolerances:
- bias within 5 reported standard deviations and within 1 count (the bias std is ~0.1-0.2
  counts from ~10 windows; 1 count = 3 mrad/s);
- sensitivity within SENS_SIGMAS = 3 reported standard deviations of the truth (the CALIB std;
  a consistent estimator misses 3 sigma with probability 0.3 %);
- static published rate: median |gyro - truth| below 0.01 rad/s (the ENC-03J's noise after the
  25 Hz low-pass is ~0.005 rad/s rms per sample; a bias error of 1 count gives 0.003 rad/s);
- moving published rate: the rms of (gyro - truth) over the samples that rotate (|truth| >
  0.1 rad/s) may exceed the static noise only by the scale uncertainty:
  rms_moving <= 1.2 * hypot(rms_static, (3 sigma_S / S + 0.002) * rms(truth)), 0.002 for the
  supply ripple (4 mV on 3.25 V modulates the count scale); 1.2 for the spread of an rms
  estimate from a few hundred samples. Measured (seed 0): 0.0046 rad/s still, 0.0050 rad/s
  moving, bound 0.012. A one-sample misalignment of the published rate against the samples
  (0.022 rad/s rms over the rotating samples of this record) or a wrong sign fails it.
"""
from __future__ import annotations

import numpy as np
import pytest
from gravcal.core.model.defaults import default_model
from gravcal.core.model.enc03j import gyro_truth
from gravcal.core.samples import SAMPLE_DTYPE
from gravcal.core.scenarios import plan_motion
from gravcal.core.simulate import (
    seed_streams,  # the emulator's seed -> (motion, model, sensor) streams
)
from scipy import signal
from support.gravcald_process import GravcaldProcess, poll

SPEED = 50.0
PITCH_SCENARIO, PITCH_DURATION_S = "sagittal_postures", 900.0
DECLINE_SCENARIO = "six_position"
BIAS_SIGMAS, BIAS_MAX_COUNTS = 5.0, 1.0
SENS_SIGMAS = 3.0
STATIC_MAX_RAD_S = 0.01
MOVING_RAD_S = 0.1  # |true rate| above which a sample counts as rotating
STILL_TRUE_RAD_S = 0.01  # |true rate| below which a sample counts as still
SUPPLY_RIPPLE_REL = 0.002
RMS_SPREAD = 1.2
N_SAMPLES = 6000  # 60 s of sensor time: several pose changes

SEED = 0  # the emulated sensor and wearer (as tests/system/test_e2e.py)
FS = 100.0


def Daemon(directory, *args: str, **kw) -> GravcaldProcess:
    return GravcaldProcess(directory, *args, seed=SEED, fs=FS, **kw)


def _collect(client, n: int) -> dict[str, np.ndarray]:
    """n IMU messages: seq, published gyro [rad/s] (NaN for null), static flag, vsupply."""
    seq, rates, static, vs = [], [], [], []
    client.set_watch(enable=True, rate=0)
    while len(seq) < n:
        m = client.read_message(timeout=30)
        if m["class"] == "IMU":
            seq.append(m["seq"])
            rates.append(np.nan if m["gyro"] is None else m["gyro"])
            static.append(bool(m["static"]))
            vs.append(m["vsupply"])
    client.set_watch(enable=False)
    return {"seq": np.asarray(seq, np.int64), "rates": np.asarray(rates, float), "static": np.asarray(static),
            "vsupply": np.asarray(vs, float)}


def _truth(samples: dict[str, np.ndarray]) -> dict:
    model = default_model(seed_streams(SEED)[1])
    return gyro_truth(model, vsupply=float(np.median(samples["vsupply"])))


def true_conditioned_rate(scenario: str, duration_s: float, seq: np.ndarray) -> np.ndarray:
    """The rate [rad/s] the board's gyro output carries at samples ``seq``: the scenario's body
    rate along the sensitive axis through the conditioning stage (the emulator's model)."""
    model = default_model(seed_streams(SEED)[1])
    plan = plan_motion(scenario, duration=duration_s, fs=FS, rng=seed_streams(SEED)[0])
    motion = plan.render(0, int(seq.max()) + 1)
    axis = np.asarray(model["gyro_sensor"].params["axis"], float)
    # starts at rest (rate 0 at sample 0): the model's settled start is the zero state here
    conditioned = signal.sosfilt(model["gyro_conditioning"].sos(FS), motion.omega @ axis)
    return conditioned[seq]


@pytest.fixture(scope="module")
def pitch_run(tmp_path_factory):
    """sagittal_postures: CALIB before any gyro calibration, the first CALIB with a determined
    sensitivity, then N_SAMPLES IMU samples and the CALIB after them."""
    d = Daemon(tmp_path_factory.mktemp("e2e-gyro-pitch"), "--bus", "serial", "--scenario", PITCH_SCENARIO,
               "--speed", str(SPEED), "--duration", str(PITCH_DURATION_S))
    try:
        d.wait_serving()
        with d.client() as c:
            first = c.calib()["gyro"]
            # seed 0 determines it at ~300 s of sensor time (6 s at 50x); 60 s allows a loaded machine
            poll(lambda: c.calib()["gyro"]["sensitivity"] is not None, 60, "a gyro sensitivity in ?CALIB", interval=0.1)
            got = _collect(c, N_SAMPLES)
            cal = c.calib()["gyro"]
    finally:
        assert d.stop() == 0
    return {"first": first, "gyro": cal, **got, "truth": _truth(got),
            "true_rate": true_conditioned_rate(PITCH_SCENARIO, PITCH_DURATION_S, got["seq"])}


@pytest.fixture(scope="module")
def decline_run(tmp_path_factory):
    """six_position: the first CALIB with a gyro bias, then 3000 IMU samples and the CALIB after."""
    d = Daemon(tmp_path_factory.mktemp("e2e-gyro-decline"), "--bus", "serial", "--scenario", DECLINE_SCENARIO,
               "--speed", str(SPEED), "--duration", "600")
    try:
        d.wait_serving()
        with d.client() as c:
            first = c.calib()["gyro"]
            poll(lambda: c.calib()["gyro"]["n_windows"] >= 1, 90, "a gyro bias in ?CALIB", interval=0.1)
            # past ~8 pose changes with the gyro running (accelerometer accepted at ~130 s)
            poll(lambda: c.calib()["gyro"]["n_windows"] >= 10, 90, "10 gyro windows in ?CALIB", interval=0.1)
            got = _collect(c, 3000)
            cal = c.calib()["gyro"]
    finally:
        assert d.stop() == 0
    return {"first": first, "gyro": cal, **got, "truth": _truth(got)}


def test_calib_has_no_gyro_values_before_the_accelerometer_is_accepted(decline_run):
    first = decline_run["first"]
    assert first["n_windows"] == 0 and first["sensitivity"] is None and first["bias"] == [None]
    assert first["applied"] == {"bias": None, "sensitivity": None}  # no [gyro] config: rate null


@pytest.mark.parametrize("which", ["decline_run", "pitch_run"])
def test_gyro_bias_reaches_calib(which, request):
    run = request.getfixturevalue(which)
    gy, truth = run["gyro"], run["truth"]
    assert gy["axes"] == 1 and gy["axis"] == [0.0, 1.0, 0.0] and gy["hp_hz"] == 0.3 and gy["n_windows"] >= 1
    bias, bias_std = gy["bias"][0], gy["std"]["b"]
    err = abs(bias - truth["bias_counts"])
    assert err < BIAS_MAX_COUNTS and err < BIAS_SIGMAS * bias_std, (bias, bias_std, truth)
    assert gy["applied"]["bias"] == bias


def test_pitch_rotations_determine_the_sensitivity_online(pitch_run):
    gy, s_true = pitch_run["gyro"], pitch_run["truth"]["sensitivity_counts_per_rad_s"]
    assert pitch_run["first"]["sensitivity"] is None  # nothing claimed at start
    assert gy["observable"] is True and gy["n_pairs"] >= 4, gy["message"]
    sens, sens_std = gy["sensitivity"][0][0], gy["std"]["S"]
    assert sens > 0 and abs(sens - s_true) < SENS_SIGMAS * sens_std, (sens, sens_std, s_true, gy["message"])
    assert gy["applied"] == {"bias": gy["bias"][0], "sensitivity": sens}
    assert gy["methods"]["sensitivity"].startswith("pose-to-pose")
    # the lying episodes' rolls to the sides are rejected for what they are, not used
    assert gy["rejected_pairs"].get("rotation not about the gyro's sensitive axis (gravity's component along it "
                                    "changed)", 0) >= 1, gy["rejected_pairs"]


def test_published_rate_is_the_true_rate(pitch_run):
    r, e, s = pitch_run["rates"], pitch_run["true_rate"], pitch_run["static"]
    gy = pitch_run["gyro"]
    assert np.isfinite(r).all(), "once bias and sensitivity are known every IMU gyro value is finite"
    moving = np.abs(e) > MOVING_RAD_S
    assert moving.sum() > 200 and np.abs(e).max() > 0.5, "the record holds pose changes to compare"
    # still by the truth, not by the published `static` (null while the daemon's analysis lags on a loaded host)
    still = np.abs(e) < STILL_TRUE_RAD_S
    assert still.sum() > 500 and s.sum() > 0
    static_err = r[still] - e[still]
    assert float(np.median(np.abs(static_err))) < STATIC_MAX_RAD_S, np.median(np.abs(static_err))
    rms_static = float(np.sqrt(np.mean(static_err**2)))
    rms_moving = float(np.sqrt(np.mean((r[moving] - e[moving]) ** 2)))
    rel = SENS_SIGMAS * gy["std"]["S"] / gy["sensitivity"][0][0] + SUPPLY_RIPPLE_REL
    bound = RMS_SPREAD * float(np.hypot(rms_static, rel * np.sqrt(np.mean(e[moving] ** 2))))
    assert rms_moving <= bound, (rms_moving, bound, rms_static)
    slope = float(r[moving] @ e[moving] / (e[moving] @ e[moving]))  # the published scale against the truth
    assert abs(slope - 1.0) < rel, slope


def test_without_rotations_about_y_the_sensitivity_is_declined_with_a_reason(decline_run):
    gy, r = decline_run["gyro"], decline_run["rates"]
    assert gy["sensitivity"] is None and gy["observable"] is False, gy
    assert gy["message"].startswith("no sensitivity:") and "rejected:" in gy["message"], gy["message"]
    assert sum(gy["rejected_pairs"].values()) >= 5, gy["rejected_pairs"]  # pose changes seen, and refused
    # no rate rather than one with a made-up scale
    assert gy["applied"]["sensitivity"] is None and np.isnan(r).all(), gy["applied"]


def test_a_resumed_state_starts_the_gyro_from_its_saved_values():
    from gravcal.daemon.config import load_config
    from gravcal.daemon.persistence import CalibrationState
    from gravcal.daemon.processing import Processor, nominal_calibration

    cfg = load_config(None, {"device.fs_hz": 100.0})
    acc = nominal_calibration()
    acc.converged = acc.observable = True
    saved = {"gyro": {"bias": [2040.0], "sensitivity": [[320.0]]}}
    p = Processor(cfg, CalibrationState(acc, 3, None, True, saved), resumed=True)
    block = np.zeros(4, dtype=SAMPLE_DTYPE)
    block["gyro"] = [2040, 2072, 2008, 2040]
    np.testing.assert_allclose(p.correct(block)[1], [0.0, 0.1, -0.1, 0.0])
    assert p.gyro_json["applied"] == {"bias": 2040.0, "sensitivity": 320.0}
    assert p.gyro_cal.start_scale == 1 / 320.0  # the estimator starts there too
    fresh = Processor(cfg, CalibrationState(acc, 0, None, False, saved), resumed=False)
    assert np.isnan(fresh.correct(block)[1]).all()  # not resumed: no gyro values, null rate
