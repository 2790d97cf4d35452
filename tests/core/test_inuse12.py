"""In-use 9 / 12: the identifiable part (S, o) is estimated, the frame R0 is held."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from gravcal.core.calibration import Calibration
from gravcal.core.crlb import cap_directions, daily_living_directions, norm_noise_var, windows_on_ellipsoid
from gravcal.core.estimators.inuse12 import fit_inuse, frame_of, identifiable_part, rotation_angle_deg, with_frame
from gravcal.core.estimators.lotters import LottersBatch
from gravcal.core.estimators.recursive import LottersRecursive
from gravcal.core.estimators.parameterization import PARAMETERIZATIONS, NineParameter, TwelveInUse, polar_frame

NOISE_G = 0.005
MOUNT2 = Rotation.align_vectors([[1, 1, 1]], [[0, 0, 1.0]])[0].as_matrix()  # Lötters' orientation 2


def misaligned(seed: int = 0) -> Calibration:
    """Full K = S R0: non-orthogonal axes (symmetric part, +-2 %) and a 3° frame rotation."""
    rng = np.random.default_rng(seed)
    D = np.diag([0.125, 0.131, 0.118])
    A = np.zeros((3, 3))
    A[2, :2] = rng.uniform(-0.02, 0.02, 2)
    A[0, 1] = rng.uniform(-0.01, 0.01)
    R = Rotation.from_rotvec(np.radians(3.0) * np.array([0.6, -0.64, 0.48])).as_matrix()
    return Calibration("truth", [0.502, 0.493, 0.508], D @ (np.eye(3) + A) @ R)


def p9(cal: Calibration) -> np.ndarray:
    S, o = identifiable_part(cal)
    return np.array([S[0, 0], S[1, 1], S[2, 2], S[0, 1], S[0, 2], S[1, 2], *o])


@pytest.mark.parametrize("cls", [NineParameter, TwelveInUse])
def test_parameterization_jacobian_and_pack(cls):
    truth = misaligned(1)
    par = cls(truth.sensitivity, truth.offset)
    assert PARAMETERIZATIONS[cls.model] is cls and par.n_params == 9
    p = par.pack(truth.sensitivity, truth.offset)
    K, o = par.unpack(p)
    np.testing.assert_allclose(K @ K.T, truth.sensitivity @ truth.sensitivity.T, atol=1e-14)  # same norm function
    if cls is TwelveInUse:
        np.testing.assert_allclose(K, truth.sensitivity, atol=1e-14)  # frame taken from K0: K itself
    else:
        np.testing.assert_allclose(K, K.T, atol=1e-15)  # R0 = I convention
    raw = np.random.default_rng(0).normal(0.5, 0.12, (20, 3))
    h, B, _ = par.norm_and_jacobian(p, raw)
    eps = 1e-7
    Bn = np.array([(par.norm_and_jacobian(p + eps * e, raw)[0] - par.norm_and_jacobian(p - eps * e, raw)[0]) / (2 * eps)
                   for e in np.eye(9)]).T
    np.testing.assert_allclose(B, Bn, rtol=1e-6, atol=1e-6)


def test_rotating_K_leaves_the_norm_unchanged():
    # the whole argument in one line: |R K^-1 (r - o)| = |K^-1 (r - o)|, i.e. K -> K R^T is invisible
    truth = misaligned(2)
    raw = np.random.default_rng(1).normal(0.5, 0.12, (50, 3))
    R = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    other = Calibration("x", truth.offset, truth.sensitivity @ R.T)
    np.testing.assert_allclose(np.linalg.norm(other.apply(raw), axis=1), np.linalg.norm(truth.apply(raw), axis=1),
                               rtol=1e-12)
    assert rotation_angle_deg(frame_of(other) @ frame_of(truth).T) == pytest.approx(math.degrees(np.linalg.norm([0.3, -0.2, 0.5])), rel=1e-9)


def session(truth, seed, m=150):
    rng = np.random.default_rng(seed)
    return windows_on_ellipsoid(truth, daily_living_directions(m, rng, MOUNT2), noise_g=NOISE_G, n=300, rng=rng)


def test_inuse12_daily_living_recovers_identifiable_part_and_holds_the_frame():
    truth = misaligned(3)
    # the lab calibration: right frame, but S and o have drifted since (what in-use must track)
    S, o = identifiable_part(truth)
    lab = Calibration("12", truth.offset + 0.004, (S * 1.01) @ frame_of(truth))
    ws = session(truth, 10)
    cal = fit_inuse(ws, "12", lab=lab, sigma_floor_g=0.0)
    assert cal.model == "12" and cal.param_names[:3] == ["s_xx", "s_yy", "s_zz"] and len(cal.param_names) == 9
    # held frame unchanged (to rounding), whatever the start's convention was
    assert rotation_angle_deg(frame_of(cal) @ frame_of(lab).T) < 1e-6
    # identifiable part recovered: chi-square test of the 9-vector against its reported covariance (p = 0.001)
    e = p9(cal) - p9(truth)
    assert e @ np.linalg.solve(cal.covariance, e) < chi2.ppf(0.999, 9)
    # full K recovered too, because the held frame is the true one
    assert np.max(np.abs(cal.sensitivity - truth.sensitivity)) < 5e-4 * 0.125
    # held-out: a second session of the same sensor; norm error at the noise level sqrt(mean var(h))
    test = session(truth, 11)
    r = 1.0 - np.linalg.norm(cal.apply(test.mean), axis=1)
    noise = math.sqrt(np.mean(norm_noise_var(test, truth)))
    rms = math.sqrt(np.mean(r * r))
    # rms^2 / noise^2 ~ chi2_M / M (+ the small estimation error): within 4 se = 4 sqrt(2 / M) of 1
    assert rms / noise < math.sqrt(1 + 4 * math.sqrt(2 / len(test)) + 0.1), (rms, noise)
    six = LottersBatch("6").fit(ws, Calibration("6", lab.offset, np.diag(np.diag(lab.sensitivity))))
    r6 = 1.0 - np.linalg.norm(six.apply(test.mean), axis=1)
    assert math.sqrt(np.mean(r6 * r6)) > 5 * rms  # no cross-axis terms: the misalignment shows


def test_inuse9_is_the_same_estimate_in_the_symmetric_convention():
    truth = misaligned(4)
    ws = session(truth, 20)
    c9 = fit_inuse(ws, "9", sigma_floor_g=0.0)
    c12 = fit_inuse(ws, "12", lab=truth, sigma_floor_g=0.0)
    np.testing.assert_allclose(c9.sensitivity, c9.sensitivity.T, atol=1e-15)
    np.testing.assert_allclose(p9(c9), p9(c12), rtol=0, atol=1e-8)
    # equal to rounding: relative 1e-5 on each entry, and an absolute floor of 1e-6 of the largest entry for
    # the near-zero off-diagonal ones (two numerically different but equivalent computations)
    np.testing.assert_allclose(c9.covariance, c12.covariance, rtol=1e-5, atol=1e-6 * np.abs(c12.covariance).max())
    assert c9.metadata["frame_source"].startswith("R0 = I")
    # the 9 model's K differs from the true K exactly by the (unobservable) frame
    assert rotation_angle_deg(frame_of(truth)) > 2.0  # 3° rotation + the antisymmetric part of the misalignment
    np.testing.assert_allclose(c9.sensitivity @ frame_of(truth), c12.sensitivity, atol=1e-6)


def test_recursive_12_keeps_the_frame():
    truth = misaligned(5)
    ws = session(truth, 30)
    start = with_frame(LottersBatch("9").fit(ws.subset(np.arange(40))), truth)
    rec = LottersRecursive(start, "12", sigma_floor_g=0.0)
    cal = rec.update(ws.subset(np.arange(40, len(ws))))
    assert rotation_angle_deg(frame_of(cal) @ frame_of(truth).T) < 1e-6
    e = p9(cal) - p9(truth)
    assert e @ np.linalg.solve(cal.covariance, e) < chi2.ppf(0.999, 9)


def test_bad_input_messages():
    truth = misaligned(6)
    rng = np.random.default_rng(0)
    ws = windows_on_ellipsoid(truth, cap_directions((0, 0, 1), 2, 30, rng), noise_g=NOISE_G, n=300, rng=rng)
    with pytest.raises(ValueError, match="model 12 holds the frame of a lab calibration"):
        fit_inuse(ws, "12")
    with pytest.raises(ValueError, match="do not determine the sensitivities and cross-axis terms"):
        fit_inuse(ws, "9", start=truth)
    with pytest.raises(ValueError, match="only 5 quasi-static window"):
        fit_inuse(ws.subset(np.arange(5)), "9", start=truth)
    with pytest.raises(ValueError, match="orthogonal"):
        with_frame(truth, np.diag([1.0, 2.0, 1.0]))
    S, R = polar_frame(truth.sensitivity)
    np.testing.assert_allclose(S @ R, truth.sensitivity, atol=1e-15)
