"""Bragge lab calibration: 12 parameters from the six faces, found without markers."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gravcal.core.calibration import Calibration
from gravcal.core.crlb import BRAGGE_NAMES, cap_directions, crlb_lab, windows_on_ellipsoid
from gravcal.core.estimators.bragge import (FACE_DIRECTIONS, FACES, bragge_fit, calibrate_faces, calibrate_lab,
                                            find_faces)

NOISE_G = 0.005  # ADXL210 noise per sample [g rms], ~500 ug/sqrt(Hz) over 50 Hz + timer quantisation
S_NOM = np.array([0.125, 0.131, 0.118])  # duty / g
O_NOM = np.array([0.502, 0.493, 0.508])  # duty


def misaligned_truth(rng) -> Calibration:
    """Chip A (x, y) nearly aligned, chip B (z) tilted: cross-axis up to +-2 % on the z row."""
    M = np.zeros((3, 3))
    M[2, :2] = rng.uniform(-0.02, 0.02, 2)
    M[0, 1], M[1, 0] = rng.uniform(-0.004, 0.004, 2)
    return Calibration("truth", O_NOM, np.diag(S_NOM) @ (np.eye(3) + M))


def theta_of(cal: Calibration) -> np.ndarray:  # eq. 2 ordering
    return np.concatenate([cal.sensitivity.ravel(order="F"), cal.offset])


def tilted(direction: np.ndarray, sd_deg: float, rng) -> np.ndarray:
    return Rotation.from_rotvec(rng.normal(0, math.radians(sd_deg), 3)).apply(direction)


def six_face_windows(truth, rng, *, sd_deg=1.0, n=800, extra=0):
    dirs = np.array([tilted(FACE_DIRECTIONS[f], sd_deg, rng) for f in rng.permutation(FACES)])
    if extra:
        dirs = np.vstack([dirs, cap_directions((1, 1, 1), 20, extra, rng)])
    return windows_on_ellipsoid(truth, dirs, noise_g=NOISE_G, n=n, rng=rng)


def test_six_positions_all_12_within_3_sigma_and_faces_found():
    rng = np.random.default_rng(7)
    truth = misaligned_truth(rng)
    ws = six_face_windows(truth, rng, extra=3)
    rep = calibrate_faces(ws)
    assert sorted(h.face for h in rep.faces) == sorted(FACES)
    for h in rep.faces:  # every face matched to the window that truly held it
        a = truth.apply(ws.mean[h.windows[0]])
        assert np.degrees(np.arccos(a @ h.direction / np.linalg.norm(a))) < 5
    cal = rep.calibration
    assert cal.model == "12" and cal.param_names == BRAGGE_NAMES
    z = (theta_of(cal) - theta_of(truth)) / np.sqrt(np.diag(cal.covariance))
    assert np.all(np.abs(z) < 3), z
    assert abs(cal.sensitivity[2, 0] - truth.sensitivity[2, 0]) < 3 * cal.std["k_31"]
    # the 3 windows near no face were not fitted and are a held-out check: norm error at the level that the
    # placement uncertainty (1 deg -> up to ~2 % cross-axis) allows
    assert rep.other_norm_rms_mg is not None and rep.other_norm_rms_mg < 20
    assert rep.heldout_rms_mg is not None and rep.heldout_rms_mg > rep.insample_rms_mg
    d = rep.to_json_dict()
    assert d["model"] == "12" and set(d["std"]) == set(BRAGGE_NAMES) and d["n_windows"] == 9
    assert d["heldout_rms_mg"] == pytest.approx(rep.heldout_rms_mg) and set(d["faces"]) == set(FACES)
    from gravcal.core.pipeline import CalibrationReport
    assert isinstance(rep, CalibrationReport)


def test_reported_covariance_is_calibrated_over_seeds():
    # z-scores of all 12 parameters over N sessions with face tilts of 1 deg rms (the assumed placement):
    # E[z^2] = 1 for an exact covariance; the Birge scaling (applied when chi2/6 > 1) makes it smaller,
    # E ~ 0.85 (so the lower bound 0.7). Upper bound: 1 + 4 se with se = sqrt(2 / (12 N)) (z^2 ~ chi2_1).
    N = 150
    z2 = []
    for seed in range(N):
        rng = np.random.default_rng(1000 + seed)
        truth = misaligned_truth(rng)
        cal = calibrate_faces(six_face_windows(truth, rng)).calibration
        z2.append(((theta_of(cal) - theta_of(truth)) ** 2 / np.diag(cal.covariance)))
    mean_z2 = float(np.mean(z2))
    se = math.sqrt(2 / (12 * N))
    assert 0.7 < mean_z2 < 1 + 4 * se, mean_z2


def test_covariance_equals_the_cramer_rao_bound_without_placement_error():
    rng = np.random.default_rng(3)
    truth = misaligned_truth(rng)
    ws = six_face_windows(truth, rng, sd_deg=0.0)
    dirs = np.array([FACE_DIRECTIONS[f] for f in FACES])
    order = [next(i for i in range(6) if np.allclose(truth.apply(ws.mean[i]), d, atol=0.02)) for d in dirs]
    cal = bragge_fit(dirs, ws.mean[order], ws.cov_of_mean[order])
    bound = crlb_lab(dirs, ws.cov_of_mean[order], truth)
    np.testing.assert_allclose(cal.covariance / cal.metadata["cov_scale"], bound.cov, rtol=1e-9)
    assert bound.identifiable and bound.accel_rms_g < 1e-3


def six_position_series(truth, rng, fs=100.0, hold_s=8.0, turn_s=3.0, faces=FACES, twice=None):
    """Time series of a hand-performed session: holds (with noise) joined by smooth rotations."""
    rots = [Rotation.align_vectors([FACE_DIRECTIONS[f]], [[0, 0, 1.0]])[0] * Rotation.from_rotvec([0, 0, rng.uniform(-3, 3)])
            for f in faces]
    if twice is not None:  # the same face again, at a clearly different attitude
        axis = np.cross(FACE_DIRECTIONS[twice[0]], [0.6, 0.0, 0.8])  # any axis not along the face normal
        axis /= np.linalg.norm(axis)
        rots.append(Rotation.from_rotvec(np.radians(twice[1]) * axis) * rots[faces.index(twice[0])])
    parts = []
    for k, r in enumerate(rots):
        if k:  # slerp from the previous attitude while lifting and setting down
            u = np.linspace(0, 1, int(turn_s * fs))
            from scipy.spatial.transform import Slerp
            sl = Slerp([0, 1], Rotation.concatenate([rots[k - 1], r]))(u)
            up = sl.apply([0, 0, 1.0])
            parts.append(up * (1 + 0.3 * np.sin(2 * np.pi * u))[:, None])  # lift and set down: vertical 0.3 g
        parts.append(np.repeat(r.apply([0, 0, 1.0])[None], int(hold_s * fs), axis=0))
    a = np.vstack(parts)
    raw = a @ truth.sensitivity.T + truth.offset + rng.normal(0, NOISE_G, a.shape) @ truth.sensitivity.T
    return np.arange(len(a)) / fs, raw


def test_calibrate_lab_from_time_series_finds_faces_without_markers():
    rng = np.random.default_rng(11)
    truth = misaligned_truth(rng)
    t, raw = six_position_series(truth, rng)
    rep = calibrate_lab(t, raw, fs=100.0)
    assert [h.face for h in rep.faces] == list(FACES)
    starts = {h.face: h.t_start for h in rep.faces}
    assert starts["+x"] < starts["-x"] < starts["+y"] < starts["-y"] < starts["+z"] < starts["-z"]  # recording order
    z = (theta_of(rep.calibration) - theta_of(truth)) / np.sqrt(np.diag(rep.calibration.covariance))
    assert np.all(np.abs(z) < 3), z


def test_simulated_six_position_session_from_the_sensor_model():
    from gravcal.core.simulate import simulate
    from gravcal.core.model.defaults import default_model
    from gravcal.core.samples import raw_triad

    model = default_model(np.random.default_rng(5), misalignment=True)
    sim = simulate("six_position", model, seed=5, duration=80.0, fs=100.0, hold_s=(10.0, 10.0), handling_s=(4.0, 4.0),
                   tilt_deg=1.0)
    truth = Calibration.from_dict(sim.truth["calibration"])
    rep = calibrate_lab(sim.samples["t"], raw_triad(sim.samples), fs=100.0, placement_deg=1.0)
    assert sorted(h.face for h in rep.faces) == sorted(FACES)
    z = (theta_of(rep.calibration) - theta_of(truth)) / np.sqrt(np.diag(rep.calibration.covariance))
    assert np.all(np.abs(z) < 3), z


def test_missing_face_is_named():
    rng = np.random.default_rng(2)
    truth = misaligned_truth(rng)
    t, raw = six_position_series(truth, rng, faces=("+x", "-x", "+y", "-y", "+z"))
    with pytest.raises(ValueError, match=r"face -z missing"):
        calibrate_lab(t, raw, fs=100.0)


def test_face_held_twice_at_different_attitudes_is_an_error_and_same_attitude_is_merged():
    rng = np.random.default_rng(4)
    truth = misaligned_truth(rng)
    t, raw = six_position_series(truth, rng, twice=("+x", 9.0))
    with pytest.raises(ValueError, match=r"face \+x held in 2 separate window clusters"):
        calibrate_lab(t, raw, fs=100.0)
    t, raw = six_position_series(truth, rng, twice=("+y", 0.5))
    rep = calibrate_lab(t, raw, fs=100.0)
    hold = next(h for h in rep.faces if h.face == "+y")
    assert len(hold.windows) == 2 and any("merged" in n for n in rep.notes)


def test_bad_input_messages():
    a = np.array([FACE_DIRECTIONS[f] for f in FACES])
    truth = misaligned_truth(np.random.default_rng(0))
    z = a @ truth.sensitivity.T + truth.offset
    with pytest.raises(ValueError, match="needs N >= 4"):
        bragge_fit(a[:3], z[:3])
    flat = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0.7071, 0.7071, 0]])  # all in the x-y plane
    with pytest.raises(ValueError, match="coplanar"):
        bragge_fit(flat, flat @ truth.sensitivity.T + truth.offset)
    with pytest.raises(ValueError, match="coplanar"):  # one posture repeated
        bragge_fit(np.repeat(a[:1], 5, axis=0), np.repeat(z[:1], 5, axis=0))
    with pytest.raises(ValueError, match="no quasi-static windows"):
        find_faces(windows_on_ellipsoid(truth, np.zeros((0, 3)), noise_g=NOISE_G, n=10, rng=np.random.default_rng(0)))
    with pytest.raises(ValueError, match="constant"):
        calibrate_lab(np.arange(1000) / 100.0, np.full((1000, 3), 0.5), fs=100.0)
