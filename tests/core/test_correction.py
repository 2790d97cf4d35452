"""The per-sample correction kernel (core/_correctkernel.c) against its numpy reference: a plain calibration's
bits (tests/support/correction_reference.py plain_block), and every term the online calibrator can publish, alone and
all together, within rounding bounds of the model Calibration.apply; a missing covariate its terms need gives NaN,
one they do not need does not."""
from __future__ import annotations

import math

import numpy as np
import pytest

from support.correction_reference import (calibration, extended_bound, extended_model, plain_block,
                                          samples_with_covariates)
from gravcal.core._correctkernel import correct_rows
from gravcal.core.correction import CP_N, UncorrectableTerm, correct, correction_params
from gravcal.core.model.terms import CALIBRATION_TERMS
from gravcal.daemon.config import ONLINE_TERMS

G = 9.80665
FS = 100.0  # samples_with_covariates' rate


@pytest.mark.parametrize("seed", range(3))
def test_plain_calibration_gives_the_references_bits_and_the_model(seed):
    rng = np.random.default_rng(seed)
    s = samples_with_covariates(seed)
    cal = calibration(rng, ())
    acc, gyro = correct(correction_params(cal, G, FS), s, 2048.0, 357.0)
    np.testing.assert_array_equal(acc, plain_block(s, cal.offset, cal.sensitivity, G))
    np.testing.assert_array_equal(gyro, (s["gyro"].astype(float) - 2048.0) / 357.0)
    np.testing.assert_allclose(acc, cal.apply_reference(plain_block(s, np.zeros(3), np.eye(3))) * G, rtol=1e-12)
    assert np.isnan(acc).any(axis=1).sum() > 0


@pytest.mark.parametrize("terms", [(t,) for t in ONLINE_TERMS] + [ONLINE_TERMS], ids=lambda t: "+".join(t))
def test_every_online_term_is_the_model_within_rounding(terms):
    for seed in range(3):
        rng = np.random.default_rng(100 + seed)
        s = samples_with_covariates(seed)
        cal = calibration(rng, tuple(t for t in CALIBRATION_TERMS if t in terms))
        got, _ = correct(correction_params(cal, G, FS), s)
        want = extended_model(cal, s, FS, G)
        np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
        ok = ~np.isnan(want).any(axis=1)
        err = np.abs(got - want)[ok].max(axis=1)
        bound = extended_bound(cal, s[ok], want[ok], G, FS)
        assert (err <= bound).all(), (terms, float((err / bound).max()))
        # the terms matter: the plain correction is far off, so a term dropped or mis-signed cannot pass
        plain = cal.apply_reference(plain_block(s, np.zeros(3), np.eye(3))) * G
        assert np.abs(plain - want)[ok].max() > 1e6 * bound.max(), terms


def test_a_missing_covariate_gives_nan_only_where_a_term_needs_it():
    rng = np.random.default_rng(7)
    s = samples_with_covariates(7)
    s["temp"][::7] = np.nan
    good = (s["t2"] != 0).all(axis=1)
    for terms, hit in ((("temperature_offset",), True), (("supply_offset",), False),
                       (("temperature_sensitivity", "supply_offset"), True)):
        got, _ = correct(correction_params(calibration(rng, terms), G, FS), s)
        assert np.isnan(got[::7][good[::7]]).all() == hit and not np.isnan(got[1::7][good[1::7]]).any(), terms


def test_the_cross_axis_term_is_in_k_and_a_lagged_term_is_refused():
    rng = np.random.default_rng(3)
    with_cross = calibration(rng, ("misalignment", "temperature_offset"))
    v = correction_params(with_cross, G, FS)
    assert v.shape == (CP_N,)
    s = samples_with_covariates(3)
    got, _ = correct(v, s)
    want = extended_model(with_cross, s, FS, G)
    ok = ~np.isnan(want).any(axis=1)
    assert (np.abs(got - want)[ok].max(axis=1) <= extended_bound(with_cross, s[ok], want[ok], G, FS)).all()
    with pytest.raises(UncorrectableTerm, match="thermal_lag needs the history"):
        correction_params(calibration(rng, ("thermal_lag",)), G, FS)


def test_correction_kernel_rejects_wrong_buffers_with_a_clear_error():
    from gravcal.core.samples import empty

    v = correction_params(calibration(np.random.default_rng(0), ()), G, FS)
    rows, acc, gyro = empty(2), np.empty(6), np.empty(2)
    with pytest.raises(ValueError, match="whole 56-byte SAMPLE_DTYPE"):
        correct_rows(rows.tobytes()[:55], v, 0.0, 1.0, acc, gyro)
    with pytest.raises(ValueError, match="params must be the CP_N"):
        correct_rows(rows, v[:5], 0.0, 1.0, acc, gyro)
    with pytest.raises(ValueError, match="acc must be 3"):
        correct_rows(rows, v, 0.0, 1.0, np.empty(4), gyro)
    with pytest.raises(TypeError):  # a read-only output
        correct_rows(rows, v, 0.0, 1.0, bytes(48), gyro)
    bad = v.copy()
    bad[26] = 0.5  # a use flag that is not 0 or 1
    with pytest.raises(ValueError, match="use flag"):
        correct_rows(rows, bad, 0.0, 1.0, acc, gyro)
    assert correct_rows(empty(0), v, math.nan, math.nan, np.empty(0), np.empty(0)) is None
