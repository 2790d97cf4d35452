"""Consider covariance (Schmidt): offsets-only fits hold the sensitivities at the start's values; when those
values are uncertain, the offsets' reported covariance must include that uncertainty (lotters.held_uncertainty,
consider_gain), and the order rule (order.is_observable) must count it."""
from __future__ import annotations

import numpy as np
import pytest

from gravcal.core.calibration import Calibration
from gravcal.core.crlb import cap_directions, sphere_directions, windows_on_ellipsoid
from gravcal.core.estimators.consider import (CONSIDER_KEY, DATASHEET_SENSITIVITY_REL_STD, HELD_KEY,
                                              datasheet_held_uncertainty, held_uncertainty, with_held_uncertainty)
from gravcal.core.estimators.lotters import LottersBatch
from gravcal.core.estimators.recursive import LottersRecursive
from gravcal.core.estimators.online import OnlineCalibrator
from gravcal.core.estimators.observability import check_observable, is_observable
from gravcal.core.estimators.parameterization import OffsetsOnly, SixParameter
from seed_pool import pmap

S0 = np.full(3, 0.04)  # ADXL210 nominal sensitivity [duty/g]
O0 = np.full(3, 0.5)  # nominal zero-g duty
NOMINAL = Calibration("nominal", O0, np.diag(S0))
UPRIGHT = (0.3, 0.2, 1.0)  # upright posture direction [g, sensor frame]; windows within 30° of it
NOISE_G, N = 0.005, 300
SEEDS = 150
CHI2_3_95 = 7.815  # 95 % quantile of chi² with 3 dof


def nees(e: np.ndarray, cov: np.ndarray) -> float:
    return float(e @ np.linalg.solve(cov, e))


def assert_chi2_3(values: list[float]) -> None:
    """Mean NEES of len(values) independent seeds vs chi² 3 dof: mean 3, variance 6/n, so 4 sigma of the
    mean is 4 sqrt(6/n) (0.8 at 150 seeds); the fraction above the 95 % quantile is binomial(n, 0.05),
    4 sigma = 4 sqrt(0.05 0.95 / n) (0.07 at 150)."""
    v = np.asarray(values)
    n = v.size
    assert abs(v.mean() - 3.0) < 4 * np.sqrt(6.0 / n), (v.mean(), np.median(v))
    assert abs(np.mean(v > CHI2_3_95) - 0.05) < 4 * np.sqrt(0.05 * 0.95 / n), np.mean(v > CHI2_3_95)


def upright_case(seed: int, rel_std: float):
    """Truth sensitivities drawn around the start's from the stated spread rel_std (the held values are off by
    that), offsets 5 % of 1 g off the start's (within the paper's start region); upright windows only."""
    rng = np.random.default_rng(seed)
    truth = Calibration("truth", O0 + rng.normal(0, 0.05 * S0), np.diag(S0 + rng.normal(0, rel_std * S0)))
    ws = windows_on_ellipsoid(truth, cap_directions(UPRIGHT, 30, 80, rng), noise_g=NOISE_G, n=N, rng=rng)
    start = with_held_uncertainty(NOMINAL, {f"s_{a}": rel_std * S0[i] for i, a in enumerate("xyz")})
    return truth, ws, start


def offsets_nees(seed: int, rel_std: float) -> tuple[float, float, float, float]:
    """One upright case's offsets NEES: (batch, batch noise-only, recursion, recursion noise-only)."""
    truth, ws, start = upright_case(seed, rel_std)
    c = LottersBatch("offsets").fit(ws.subset(np.arange(40)), start)
    e = c.offset - truth.offset
    rec = LottersRecursive(c, "offsets", sigma_floor_g=c.metadata["sigma_floor_g"])
    cr = rec.update(ws.subset(np.arange(40, 80)))
    er = cr.offset - truth.offset
    return (nees(e, c.covariance), nees(e, np.asarray(c.metadata[CONSIDER_KEY]["covariance_noise_only"])),
            nees(er, cr.covariance), nees(er, rec.P))


@pytest.mark.parametrize("rel_std", [0.02, DATASHEET_SENSITIVITY_REL_STD])
def test_offsets_nees_is_chi2_with_the_consider_term_and_not_without(rel_std):
    """Batch fit on 40 upright windows, then the recursion (seeded from it) on 40 more: with the consider term
    the offsets' NEES against the truth is chi² 3 dof; with the window noise alone (the old covariance) it is
    thousands: the offsets absorb the held sensitivities' error (the failure mode is real)."""
    b, b0, r, r0 = (list(v) for v in zip(*pmap(offsets_nees, [(seed, rel_std) for seed in range(SEEDS)])))
    assert_chi2_3(b)
    assert_chi2_3(r)
    for v in (b0, r0):  # without it: far outside chi² 3 (mean 3 +- 0.8), most seeds beyond the 95 % quantile
        assert np.mean(v) > 100 and np.mean(np.asarray(v) > CHI2_3_95) > 0.8, (np.mean(v), np.median(v))


def test_recursion_itself_is_unchanged_by_the_consider_term():
    """The consider term enters the reported covariance only: same estimate and same filter P with and
    without a stated held uncertainty; the reported covariance is P + S C_h S^T, larger."""
    truth, ws, start = upright_case(1, 0.05)
    plain = Calibration("nominal", start.offset, start.sensitivity)
    a, b = LottersRecursive(start, "offsets", sigma_floor_g=0.002), LottersRecursive(plain, "offsets", sigma_floor_g=0.002)
    ca, cb = a.update(ws), b.update(ws)
    assert np.array_equal(a.p, b.p) and np.array_equal(a.P, b.P) and a.n_rejected == b.n_rejected
    assert np.allclose(cb.covariance, b.P) and CONSIDER_KEY not in cb.metadata
    S = np.asarray(ca.metadata[CONSIDER_KEY]["sensitivity"])
    assert np.allclose(ca.covariance, a.P + S @ np.diag((0.05 * S0) ** 2) @ S.T)
    assert np.all(np.diag(ca.covariance) > 10 * np.diag(a.P))


def test_start_from_a_good_six_parameter_fit_keeps_a_small_std():
    """A sensor calibrated by a 6-parameter fit on all orientations, then run offsets-only on upright data:
    the held sensitivities' uncertainty is that fit's covariance, so the offsets' std barely grows (< 0.3 mg
    added, vs ~100 mg from a datasheet start), the order rule still says observable, and the NEES over seeds
    (held values off by the 6-fit's actual error) is chi² 3."""
    values, added_mg = [], []
    for seed in range(SEEDS // 3):
        rng = np.random.default_rng(1000 + seed)
        truth = Calibration("truth", O0 + rng.normal(0, 0.05 * S0), np.diag(S0 * (1 + rng.normal(0, 0.05, 3))))
        everywhere = windows_on_ellipsoid(truth, sphere_directions(60), noise_g=NOISE_G, n=N, rng=rng)
        c6 = LottersBatch("6").fit(everywhere, NOMINAL)
        assert c6.observable and c6.param_names == ["s_x", "s_y", "s_z", "o_x", "o_y", "o_z"]
        ws = windows_on_ellipsoid(truth, cap_directions(UPRIGHT, 30, 80, rng), noise_g=NOISE_G, n=N, rng=rng)
        c = LottersBatch("offsets").fit(ws, c6)
        cons = c.metadata[CONSIDER_KEY]
        assert cons["held"] == ["s_x", "s_y", "s_z"] and "covariance" in cons["held_source"]
        std_total = np.sqrt(np.diag(c.covariance))
        std_noise = np.sqrt(np.diag(np.asarray(cons["covariance_noise_only"])))
        added_mg.append(np.max(std_total - std_noise) / S0[0] * 1e3)
        assert c.observable
        ok, obs = is_observable(ws, c6, "offsets")
        # the consider part adds in quadrature: the predicted error moves by < 1 %
        assert ok and obs["consider_mg"] < 0.2 * obs["predicted_mg"]
        assert obs["predicted_mg"] < 1.01 * obs["predicted_given_held_mg"]
        values.append(nees(c.offset - truth.offset, c.covariance))
    assert max(added_mg) < 0.3, added_mg
    assert_chi2_3(values)


def test_is_observable_flags_offsets_from_a_nominal_start_on_upright_data():
    truth, ws, _ = upright_case(7, DATASHEET_SENSITIVITY_REL_STD)
    start = datasheet_held_uncertainty(NOMINAL)
    ok_plain, plain = is_observable(ws, NOMINAL, "offsets")  # held sensitivities taken as exact: the old verdict
    ok, obs = is_observable(ws, start, "offsets")
    assert ok_plain and plain["consider_mg"] == 0.0 and plain["predicted_mg"] < 10
    assert not ok and obs["consider_mg"] > 30 and obs["predicted_mg"] > 30
    assert obs["held"]["names"] == ["s_x", "s_y", "s_z"] and obs["predicted_given_held_mg"] == plain["predicted_mg"]
    # the batch fit: observable=False, honest std, message saying why and what would fix it
    c = LottersBatch("offsets").fit(ws, start)
    assert not c.observable
    assert "uncertainty of the held sensitivities" in c.message and "dominates" in c.message and "lying" in c.message
    err_mg = np.abs(c.offset - truth.offset) / S0 * 1e3
    std_mg = np.sqrt(np.diag(c.covariance)) / S0 * 1e3
    noise_mg = np.sqrt(np.diag(np.asarray(c.metadata[CONSIDER_KEY]["covariance_noise_only"]))) / S0 * 1e3
    assert np.max(err_mg) > 10 * np.max(noise_mg)  # the old std missed the bias by far ...
    assert np.all(err_mg < 4 * std_mg)  # ... the consider std covers it
    with pytest.raises(ValueError, match="held sensitivities"):
        check_observable(ws, "offsets", start, tol_g=0.010)


def test_online_fits_offsets_provisionally_then_six_when_lying_comes():
    """OnlineCalibrator from a datasheet start: upright windows give offsets fitted provisionally (better than
    the start, honest std, NOT observable, with the reason); lying/bending windows then determine order 6."""
    rng = np.random.default_rng(11)
    truth = Calibration("truth", O0 + 0.004 * np.array([1, -2, 1.5]), np.diag(S0 * np.array([1.07, 0.95, 1.04])))
    oc = OnlineCalibrator(datasheet_held_uncertainty(NOMINAL), systematic_g=0.0)
    upright = windows_on_ellipsoid(truth, cap_directions(UPRIGHT, 30, 60, rng), noise_g=NOISE_G, n=N, rng=rng)
    cal = oc.update(upright)
    assert oc.model == "offsets" and oc.provisional and not cal.observable
    assert "provisionally" in cal.message and "held sensitivities" in cal.message
    err = np.abs(cal.offset - truth.offset)
    assert np.max(err) < np.max(np.abs(NOMINAL.offset - truth.offset)) / 3  # moved towards the truth
    assert np.all(err < 4 * np.sqrt(np.diag(cal.covariance)))  # and says how uncertain it is
    assert np.max(np.sqrt(np.diag(cal.covariance))) / S0[0] > 0.010  # ... > the 10 mg rule
    lying = windows_on_ellipsoid(truth, sphere_directions(80), noise_g=NOISE_G, n=N, rng=rng)
    cal = oc.update(lying)
    assert oc.model == "6" and not oc.provisional and cal.observable
    assert np.max(np.abs(cal.offset - truth.offset) / S0) < 0.002


def test_held_uncertainty_sources_projection_and_persistence():
    six = SixParameter(NOMINAL.sensitivity, NOMINAL.offset)
    offs = OffsetsOnly(NOMINAL.sensitivity, NOMINAL.offset)
    start = datasheet_held_uncertainty(NOMINAL)
    assert held_uncertainty(NOMINAL, offs) is None  # nothing stated: held values exact (the old behaviour)
    assert held_uncertainty(start, six) is None  # 6 estimates everything stated
    h = held_uncertainty(start, offs)  # offsets-only: the offsets' own prior is projected out
    assert h.names == ["s_x", "s_y", "s_z"]
    assert np.allclose(np.sqrt(np.diag(h.cov)), DATASHEET_SENSITIVITY_REL_STD * S0)
    # a fit carries its held uncertainty forward (JSON round trip), so offsets -> offsets keeps it
    truth, ws, _ = upright_case(3, 0.03)
    c = LottersBatch("offsets").fit(ws, start)
    again = Calibration.from_json(c.to_json())
    assert again.metadata[HELD_KEY]["names"] == ["s_x", "s_y", "s_z"]
    c2 = LottersBatch("offsets").fit(ws, again)
    assert np.allclose(np.sqrt(np.diag(c2.covariance)), np.sqrt(np.diag(c.covariance)), rtol=0.05)
    with pytest.raises(ValueError, match="unknown held parameter"):
        with_held_uncertainty(NOMINAL, {"gain_x": 0.1})
    with pytest.raises(ValueError, match="covariance"):
        with_held_uncertainty(NOMINAL, names=["s_x"], cov=np.array([[-1.0]]))
