"""The Python path's correction (Processor.correct, by the engine) of one sample gives the numbers the block
correction gives, bit for bit, and both equal the calibration's model: a = K^-1 (raw - o) for a plain one, every
term at each sample's covariates for an extended one; a calibration the engine cannot apply is refused."""
from __future__ import annotations

import numpy as np
import pytest

from gravcal.core.calibration import Calibration
from gravcal.core.correction import UncorrectableTerm
from gravcal.core.model.terms import CALIBRATION_TERMS
from gravcal.core.simulate import simulate
from gravcal.daemon.config import ONLINE_TERMS, load_config
from gravcal.daemon.persistence import CalibrationState
from gravcal.daemon.processing import Processor, nominal_calibration
from gravcal.daemon.protocol import STANDARD_GRAVITY
from support.correction_reference import calibration, extended_bound, extended_model, samples_with_covariates

FS = 100.0


def _processor(rng: np.random.Generator) -> Processor:
    cfg = load_config(None, {"device.fs_hz": FS, "gyro.zero_counts": float(rng.uniform(1800, 2200)),
                             "gyro.counts_per_rad_s": float(rng.uniform(300, 400))})
    p = Processor(cfg, CalibrationState(nominal_calibration(), 0, None, False, {}), resumed=False)
    nominal = nominal_calibration()
    sens = np.asarray(nominal.sensitivity) + rng.normal(0, 0.002, (3, 3))  # cross-axis terms too
    p.applied = Calibration(offset=np.asarray(nominal.offset) + rng.normal(0, 0.02, 3), sensitivity=sens,
                            model=nominal.model)
    return p


@pytest.mark.parametrize("seed", range(5))
def test_one_sample_correction_equals_the_block_correction_bit_for_bit(seed):
    rng = np.random.default_rng(seed)
    samples = simulate("daily_living", seed=seed, duration=20.0, fs=FS).samples
    samples["t2"][rng.integers(0, samples.shape[0], 20), rng.integers(0, 2, 20)] = 0  # missing periods -> NaN
    p = _processor(rng)
    p.analyse(samples[:1000])  # a detector decision, so `static` is not only unknown
    acc_b, gyro_b, st_b = p.correct(samples)
    one = [p.correct(samples[i:i + 1]) for i in range(samples.shape[0])]
    acc_1 = np.concatenate([o[0] for o in one])
    gyro_1 = np.concatenate([o[1] for o in one])
    st_1 = np.concatenate([o[2] for o in one])
    assert acc_1.shape == acc_b.shape and acc_1.dtype == acc_b.dtype
    np.testing.assert_array_equal(acc_1, acc_b)  # NaN where a period is missing, in both
    np.testing.assert_array_equal(gyro_1, gyro_b)
    np.testing.assert_array_equal(st_1, st_b)
    assert st_1.dtype == st_b.dtype and np.isnan(acc_b).any(axis=1).sum() > 0
    # and both are the model: a = K^-1 (raw - o) [g] in m/s²
    cal = p.applied
    duty = samples["t1"][:, :3] / np.where(samples["t2"][:, [0, 0, 1]] == 0, np.nan, samples["t2"][:, [0, 0, 1]])
    want = np.linalg.solve(np.asarray(cal.sensitivity), (duty - np.asarray(cal.offset)).T).T * STANDARD_GRAVITY
    np.testing.assert_allclose(acc_b, want, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("terms", [("temperature_offset", "supply_offset"), ONLINE_TERMS], ids=lambda t: "+".join(t))
def test_the_python_paths_blocks_are_corrected_by_the_engine_with_every_term(terms):
    """Processor.correct (the blocks the Python path publishes) corrects an extended calibration by the engine:
    the model Calibration.apply at each sample's temperature, supply and time, within rounding bounds, one sample
    or a block alike, bit for bit."""
    rng = np.random.default_rng(5)
    samples = samples_with_covariates(5, FS)
    p = _processor(rng)
    cal = calibration(rng, tuple(t for t in CALIBRATION_TERMS if t in terms))
    p.applied = cal
    acc, _, _ = p.correct(samples)
    want = extended_model(cal, samples, FS, STANDARD_GRAVITY)
    ok = ~np.isnan(want).any(axis=1)
    np.testing.assert_array_equal(np.isnan(acc), np.isnan(want))
    assert (np.abs(acc - want)[ok].max(axis=1) <= extended_bound(cal, samples[ok], want[ok], STANDARD_GRAVITY, FS)).all()
    one = np.concatenate([p.correct(samples[i:i + 1])[0] for i in range(0, samples.shape[0], 37)])
    np.testing.assert_array_equal(one, acc[::37])


def test_a_calibration_whose_terms_need_the_history_is_refused_naming_the_term():
    cfg = load_config(None, {"device.fs_hz": FS})
    lag = Calibration("6+thermal_lag", np.full(3, 0.5), 0.04 * np.eye(3),
                      metadata={"extended": {"terms": ["thermal_lag"]}, "params": {"oL_x": 1e-4, "oL_y": 0.0, "oL_z": 0.0}})
    with pytest.raises(UncorrectableTerm, match="thermal_lag needs the history"):
        Processor(cfg, CalibrationState(lag, 0, None, False, {}), resumed=False)
